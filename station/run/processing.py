"""H(f) per step stored beside the recording as ``processed/steps``: the identification's own frequency response.

There is one producer of H(f): ``station.ident.response.checked.checked_response``, the sine fits of the raw
record windows (IEEE 1057 fits at the crank frequency found by a four-parameter fit of the
displacement, harmonics as nuisance terms) behind the identification's plausibility checks.  What
``processed/steps`` holds, what the daemon's results and the report show, and what the parameters were
fitted to are therefore the same numbers.  (A zero-phase low-pass and resampling before the fits,
as this module once did, cannot change H at the fundamental: the sine fit is itself the narrowest
band-pass, and the filter's edge transients only cost samples.)

H(f) per step in V/(m/s^2): the force-signal phasor divided by the frame-acceleration phasor, with
the 2x2 covariance of its real and imaginary parts.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from station.errors import StationError
from station.ident.response.checked import CheckedResponse, checked_response
from station.recording import Recording, read_recording, write_result

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StepResponse:
    """H(f) of one step, H = force signal / frame acceleration in V/(m/s^2) (the transfer function
    of paper Eq. 8/9 times the sensitivity); cov of (Re H, Im H); amplitudes of displacement (m) and
    force signal (V), force offset (V), residual RMS of each channel, samples used."""

    index: int
    frequency_hz: float
    frequency_std_hz: float
    H: complex
    H_cov: np.ndarray
    displacement_amplitude_m: float
    force_amplitude_V: float
    force_offset_V: float
    displacement_residual_rms_m: float
    force_residual_rms_V: float
    n_samples: int


def step_responses(cr: CheckedResponse) -> list[StepResponse]:
    """The steps of a checked response (the ones the identification uses), one StepResponse each."""
    out = []
    for k, (index, sig) in enumerate(zip(cr.used, cr.sigs, strict=True)):
        fx = sig.fit_x
        H = complex(cr.frf.H[k])
        accel = (2 * math.pi * fx.frequency_hz) ** 2 * abs(fx.phasor)
        out.append(StepResponse(index, fx.frequency_hz, fx.frequency_std_hz, H, np.asarray(cr.frf.cov[k]),
                                abs(fx.phasor), abs(H) * accel, float(cr.frf.force_offset_V[k]),
                                fx.residual_rms, float(cr.frf.force_rms_residual_V[k]), int(sig.t.size)))
    return out


def process_recording(path: str | Path, rec: Recording | None = None,
                      response: CheckedResponse | None = None) -> list[StepResponse]:
    """Store H(f) of a complete recording as ``processed/steps`` beside it (``rec``: the recording already read
    from ``path``; ``response``: its checked response if already computed, to save doing it twice).
    Steps left out are listed with the check that left them out."""
    rec = rec if rec is not None else read_recording(path)
    if not rec.complete:
        raise StationError(f"{rec.path}: the recording is incomplete ({rec.reason}); recover it first")
    cr = response if response is not None else checked_response(rec)
    out = step_responses(cr)
    why: dict[int, str] = {}
    for c in cr.checks:
        if c.step is not None and c.step not in cr.used and c.severity != "info":
            why.setdefault(c.step, c.message)
    skipped = [{"step": i, "reason": r} for i, r in sorted(why.items())]
    payload = {"producer": "station.ident.response.checked.checked_response (sine fits of the raw record windows)",
               "skipped": skipped,
               "units": {"frequency_hz": "Hz", "H": "V/(m/s^2)", "H_cov": "(V/(m/s^2))^2",
                         "displacement_amplitude_m": "m", "force_amplitude_V": "V", "t_center_s": "s",
                         "X_h": "m"},
               "steps": [{k: (v if not isinstance(v, complex) else [v.real, v.imag])
                          for k, v in asdict(s).items() if k != "H_cov"} for s in out]}
    n_h = max((sig.X_h.size for sig in cr.sigs), default=1)
    X_h = np.zeros((len(cr.sigs), n_h), dtype=complex)
    for k, sig in enumerate(cr.sigs):
        X_h[k, : sig.X_h.size] = sig.X_h
    arrays = {"frequency_hz": np.array([s.frequency_hz for s in out]),
              "H": np.array([s.H for s in out], dtype=complex),
              "H_cov": np.array([s.H_cov for s in out]).reshape(-1, 2, 2),
              "t_center_s": np.array([sig.fit_x.t_center_s for sig in cr.sigs], dtype=float),
              "X_h": X_h}
    write_result(path, "steps", payload, arrays, group="processed")
    log.info("processed %d steps of %s (%d skipped)", len(out), rec.path.name, len(skipped))
    return out
