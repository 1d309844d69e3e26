"""The decomposed recording in the padded, vectorised form the model fits work on.

Force slots (n_f = 2 K_MAX + 3 + 2 H): [crank harmonics k = 1..K_MAX as (a, b)], [poly 1, tau/h,
(tau/h)^2], [mains harmonics h = 1..H as (a, b)]; a step's absent columns (k > K, merged mains lines)
are zero in ``Rf``/``cf``.  Displacement slots: crank harmonics k = 2..K_MAX.  For each step s the
whitened force residual is  w = Rf[s] (cf[s] - m) / sigma_f[s]  and ||w||^2 sigma_f^2 is the part of
the time-domain residual energy the model can change (the LS residual energy ``ssr_f`` is the rest).
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtrc  # scipy.stats.chi2.sf is chdtrc: the same numbers without importing scipy.stats

from station.discrepancy.decompose import (
    FLAT_TOP,
    K_MAX,
    MAINS_H_MAX,
    MAINS_RANGE_HZ,
    FrequencyNotDetermined,
    StepDecomposition,
    basis_frequencies,
    decompose_step,
    windows_of,
)
from station.discrepancy.spectrum import MainsDetection, detect_mains, normalised_periodogram, significant_lines
from station.errors import StationError
from station.kept import Kept, content_key
from station.recording import Recording

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]
log = logging.getLogger(__name__)
G = 9.80665


@dataclass(frozen=True)
class RigData:
    """Everything the fits need, stacked over the n steps (see module docstring for the slots).

    f_hz (n,), x1 (n,) complex displacement fundamental (m), x1_cov (n, 2, 2), t_mid_s (n,), half_s (n,),
    kmask (n, K_MAX) bool, Rf (n, n_f, n_f) / cf (n, n_f) / sigma_f (n,) / ssr_f (n,) / n_samples (n,),
    Rd (n, 2 (K_MAX-1), 2 (K_MAX-1)) / cd / sigma_d (n,) for the displacement harmonics,
    merge (n, H) int: crank harmonic index a mains line falls on (0 = own slot);
    Rx (n, n_x, n_f) / bx (n, n_x): the rows of R of the nuisance lines outside the catalogue, so that
    their part of the gap is ||bx + Rx (cf - m)||^2 (V^2) for model coefficients m.
    Masses in kg, capacity in N, nominal sensitivity in V/N (either sign); excluded: (step index,
    reason) of windows left out (clipped).
    """

    steps: tuple[StepDecomposition, ...]
    f_hz: FloatArray
    x1: ComplexArray
    x1_cov: FloatArray
    t_mid_s: FloatArray
    half_s: FloatArray
    kmask: NDArray[np.bool_]
    Rf: FloatArray
    cf: FloatArray
    sigma_f: FloatArray
    ssr_f: FloatArray
    n_samples: FloatArray
    Rd: FloatArray
    cd: FloatArray
    sigma_d: FloatArray
    merge: NDArray[np.int64]
    Rx: FloatArray
    bx: FloatArray
    mains: MainsDetection
    load_mass_kg: float
    end_mass_kg: float
    capacity_N: float
    sensitivity_nominal: float
    sample_rate_hz: float
    excluded: tuple[tuple[int, str], ...] = ()
    common_clock: bool = True  # False: the steps' windows overlap in time (each has its own time origin)
    driven: tuple[bool, ...] = ()  # per harmonic k = 1..K_MAX: the recorded motion's D_k drives the model

    def motion_harmonics(self) -> NDArray[np.bool_]:
        """(K_MAX,) harmonics of the recorded frame motion that drive the model (``driven``; all
        when not set)."""
        return np.array(self.driven, dtype=bool) if self.driven else np.ones(K_MAX, dtype=bool)

    @property
    def n_steps(self) -> int:
        return int(self.f_hz.size)

    @property
    def n_mains(self) -> int:
        return int(self.merge.shape[1])

    @property
    def total_mass_kg(self) -> float:
        return self.load_mass_kg + self.end_mass_kg

    def noise_floor_V(self) -> float:
        """RMS of the force-channel noise over all record windows (V): sqrt(sum N sigma^2 / sum N)."""
        return float(np.sqrt(np.sum(self.n_samples * self.sigma_f**2) / np.sum(self.n_samples)))


def _stack(steps: list[StepDecomposition], n_mains: int) -> dict[str, np.ndarray]:
    n = len(steps)
    nf = 2 * K_MAX + 3 + 2 * n_mains
    nd = 2 * (K_MAX - 1)
    Rf, cf = np.zeros((n, nf, nf)), np.zeros((n, nf))
    Rd, cd = np.zeros((n, nd, nd)), np.zeros((n, nd))
    kmask = np.zeros((n, K_MAX), dtype=bool)
    merge = np.zeros((n, n_mains), dtype=np.int64)
    nx = max((s.n_extra for s in steps), default=0)
    Rx, bx = np.zeros((n, nx, nf)), np.zeros((n, nx))
    for i, s in enumerate(steps):
        kmask[i, : s.K] = True
        slots = list(range(2 * s.K)) + [2 * K_MAX + j for j in range(3)]
        for h, k in enumerate(s.mains_merge):
            merge[i, h] = k
            if k == 0:
                slots += [2 * K_MAX + 3 + 2 * h, 2 * K_MAX + 4 + 2 * h]
        sl = np.array(slots)
        e = s.n_extra
        Rf[i][np.ix_(sl, sl)] = s.force.R[e:, e:]
        cf[i, sl] = s.force.coef[e:]
        if e:
            Rx[i][np.ix_(np.arange(e), sl)] = s.force.R[:e, e:]
            bx[i, :e] = s.force.R[:e, :e] @ s.force.coef[:e]
        m = 2 * (s.K - 1)
        if m:
            Rd[i, :m, :m] = s.disp.R[-m:, -m:]
            cd[i, :m] = s.disp.coef[-m:]
    return {"Rf": Rf, "cf": cf, "Rd": Rd, "cd": cd, "kmask": kmask, "merge": merge, "Rx": Rx, "bx": bx}


def significant_motion(Rd: FloatArray, cd: FloatArray, sigma_d: FloatArray, alpha: float = 1e-6
                       ) -> tuple[bool, ...]:
    """Per harmonic k = 1..K_MAX whether the displacement channel holds significant structure at k
    over the steps (chi^2 of the marginal (a, b) of each step, 2 dof per step, p < alpha); k = 1
    always.  Harmonics within the noise (and the displacement ADC's quantisation residue) are the
    ideal sine's zeros, not an input: feeding noise into the force model would only cost precision."""
    out = [True]
    n = cd.shape[0]
    for k in range(2, K_MAX + 1):
        cols = [2 * k - 4, 2 * k - 3]
        c2, dof = 0.0, 0
        for i in range(n):
            valid = np.nonzero(np.any(Rd[i] != 0, axis=0))[0]
            if not set(cols) <= set(valid.tolist()):
                continue
            Rv = Rd[i][np.ix_(valid, valid)]
            pos = [int(np.nonzero(valid == c)[0][0]) for c in cols]
            C = sigma_d[i] ** 2 * np.linalg.inv(Rv.T @ Rv)[np.ix_(pos, pos)]
            e = cd[i, cols]
            c2 += float(e @ np.linalg.solve(C, e))
            dof += 2
        out.append(bool(dof) and float(chdtrc(dof, c2)) < alpha)
    return tuple(out)


def _common_clock(steps: list[StepDecomposition]) -> bool:
    """Whether the step windows lie on one time axis: in recording order, none starts before the
    previous one ends (an import may give every step its own time origin: then phases of lines that
    run through the whole recording, e.g. mains, are not comparable between steps)."""
    return all(b.t_mid_s - b.half_s >= a.t_mid_s + a.half_s - 1e-9 for a, b in itertools.pairwise(steps))


def _outside_lines(s: StepDecomposition, f_mains: float | None, fs: float, max_lines: int = 12,
                   spectrum: tuple[FloatArray, FloatArray] | None = None) -> tuple[float, ...]:
    """Significant lines (alpha 1e-4 over the bins) of the force residual that are not basis
    frequencies (further than 1.5 bins from them and from DC); ``spectrum``: the residual's
    periodogram when already computed."""
    res = fs / s.n_samples
    held = [*basis_frequencies(s, f_mains), 0.0]
    found = significant_lines(s.force.residual, s.force.sigma, fs, s.index, 1e-4, spectrum=spectrum)
    keep = [ln.frequency_hz for ln in found if min(abs(ln.frequency_hz - f) for f in held) > 1.5 * res]
    return tuple(keep[:max_lines])


MIN_CYCLES = 1.0


def _too_short(window_s: float, f_hz: float) -> str:
    """Why a record window cannot enter the model-gap analysis ('' if it can): a frequency that is not
    positive, or less than ``MIN_CYCLES`` crank cycles (the crank frequency, the fundamental and the
    quadratic trend of the window are then not separable: a fit of less than a cycle can return any
    frequency, even a negative one, and blame the drive)."""
    if not (f_hz > 0 and math.isfinite(f_hz)):
        return f"step left out: its crank frequency {f_hz:.4g} Hz is not positive"
    if window_s * f_hz < MIN_CYCLES:
        return (f"step left out: its record window ({window_s:.3g} s) holds {window_s * f_hz:.2g} cycles of "
                f"{f_hz:.4g} Hz; the model-gap analysis needs at least {MIN_CYCLES:g}")
    return ""


_T = TypeVar("_T")


def per_data_set(size: int) -> Callable[[Callable[[RigData], _T]], Callable[[RigData], _T]]:
    """A function of a data set made once per data set: its value for the ``size`` most recent
    ``RigData`` objects (a frozen one: the thousands of model evaluations of one analysis share what
    depends on the data alone), by identity (the data set is kept with it, so an id is never mistaken
    for a later object's)."""

    def keep(fn: Callable[[RigData], _T]) -> Callable[[RigData], _T]:
        kept: dict[int, tuple[RigData, _T]] = {}

        @functools.wraps(fn)
        def once(data: RigData) -> _T:
            hit = kept.get(id(data))
            if hit is not None and hit[0] is data:
                return hit[1]
            value = fn(data)
            if len(kept) >= size:
                del kept[next(iter(kept))]  # the oldest
            kept[id(data)] = (data, value)
            return value

        return once

    return keep


_PREPARED: Kept[RigData] = Kept(4, lambda data: data)  # the same frozen RigData given again (``prepare``)


def _content_key(rec: Recording) -> bytes:
    """A digest of everything ``prepare`` reads of a recording: the channels, the steps, the step
    documents' time origins, the rate, the masses, the capacity, the sensitivity and the path (its
    messages name it)."""
    t0 = [(d.get("index"), d.get("t0_s")) for d in rec.documents if d.get("kind") == "step"]
    return content_key(rec.displacement_m, rec.force_V, settings=(
        str(rec.path), rec.sample_rate_hz, rec.steps, t0, rec.load_mass_kg, rec.end_mass_kg, rec.capacity_N,
        rec.sensitivity_V_per_N))


def prepare(rec: Recording) -> RigData:
    """Decompose every usable step (twice: without mains lines to search them, then with them).

    A function of the recording's content: the same content asked again (the text and the JSON of one
    recording, the daemon's analysis after the command's) gives the same frozen ``RigData`` again, so
    that the fits kept for it (``fit.fit_model``) are given again too (the few most recent are kept)."""
    return _PREPARED.get(_content_key(rec), lambda: _prepare(rec))


def _prepare(rec: Recording) -> RigData:
    wins = windows_of(rec)
    if not wins:
        raise StationError(f"{rec.path}: the workflow needs at least 1 usable step, found none")
    fs = rec.sample_rate_hz
    short = [(w.index, _too_short(w.force_V.size / fs, w.f_nominal_hz)) for w in wins]
    wins = [w for w, (_, why) in zip(wins, short, strict=True) if not why]
    first, kept = [], []
    for w in wins:
        try:
            first.append(decompose_step(w, fs, None, 0))
            kept.append(w)
        except FrequencyNotDetermined as e:  # about one cycle: the fit cannot tell the frequency
            window_s = w.force_V.size / fs
            short.append((w.index, f"step left out: its record window ({window_s:.3g} s) holds "
                                   f"{window_s * w.f_nominal_hz:.2g} cycles of {w.f_nominal_hz:.4g} Hz and {e}"))
    wins = kept
    bad = [_too_short(s.n_samples / fs, s.f_hz) for s in first]  # the fitted frequency, too
    short += [(s.index, why) for s, why in zip(first, bad, strict=True) if why]
    wins = [w for w, why in zip(wins, bad, strict=True) if not why]
    first = [s for s, why in zip(first, bad, strict=True) if not why]
    excluded: tuple[tuple[int, str], ...] = tuple((i, why) for i, why in short if why)
    for i, why in excluded:
        log.warning("step %d: %s", i, why)
    if not wins:
        raise StationError(f"{rec.path}: no step's record window holds a full crank cycle ("
                           + "; ".join(f"step {i}: {why}" for i, why in excluded) + "): nothing to analyse")
    # a clipped window is not data about the rig: leave it out (and say so) while 2 steps remain
    clipped = [s.flat_top >= FLAT_TOP for s in first]
    if any(clipped) and len(wins) - sum(clipped) >= 1:
        excluded += tuple((s.index, f"force signal clipped (flat tops of {s.flat_top} samples at the window "
                                    f"extreme); step left out") for s, c in zip(first, clipped, strict=True) if c)
        wins = [w for w, c in zip(wins, clipped, strict=True) if not c]
        first = [s for s, c in zip(first, clipped, strict=True) if not c]
        for i, why in excluded:
            if "clipped" in why:
                log.warning("step %d: %s", i, why)
    spectra = [normalised_periodogram(s.force.residual, s.force.sigma, fs) for s in first]
    det = detect_mains([s.force.residual for s in first], [s.force.sigma for s in first], fs,
                       MAINS_RANGE_HZ, MAINS_H_MAX, spectra=spectra)
    log.info("mains search: %s", det.evidence)
    second = first if det.frequency_hz is None else [
        decompose_step(w, fs, det.frequency_hz, det.harmonics, f_start=s.f_hz)
        for w, s in zip(wins, first, strict=True)]
    # without mains lines the residuals are the first pass's: their periodograms are at hand
    extra = [_outside_lines(s, det.frequency_hz, fs, spectrum=sp if second is first else None)
             for s, sp in zip(second, spectra, strict=True)]
    steps = [decompose_step(w, fs, det.frequency_hz, det.harmonics, x, f_start=s.f_hz) if x else s
             for w, s, x in zip(wins, second, extra, strict=True)]
    st = _stack(steps, det.harmonics)
    if rec.end_mass_kg is None:
        log.warning("%s: no end mass in the recording; m_e = 0 assumed (M = load mass)", rec.path)
    return RigData(
        steps=tuple(steps), f_hz=np.array([s.f_hz for s in steps]), x1=np.array([s.x1 for s in steps]),
        x1_cov=np.array([s.x1_cov for s in steps]), t_mid_s=np.array([s.t_mid_s for s in steps]),
        half_s=np.array([s.half_s for s in steps]), kmask=st["kmask"], Rf=st["Rf"], cf=st["cf"],
        sigma_f=np.array([s.force.sigma for s in steps]), ssr_f=np.array([s.force.ssr for s in steps]),
        n_samples=np.array([s.n_samples for s in steps], dtype=float), Rd=st["Rd"], cd=st["cd"],
        sigma_d=np.array([s.disp.sigma for s in steps]), merge=st["merge"], Rx=st["Rx"], bx=st["bx"], mains=det,
        load_mass_kg=rec.load_mass_kg, end_mass_kg=rec.end_mass_kg or 0.0, capacity_N=rec.capacity_N,
        sensitivity_nominal=rec.sensitivity_V_per_N, sample_rate_hz=fs, excluded=excluded,
        common_clock=_common_clock(second),
        driven=significant_motion(st["Rd"], st["cd"], np.array([s.disp.sigma for s in steps])))
