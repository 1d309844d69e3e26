"""Processing of a recording before identification: zero-phase low-pass filter, polyphase
resampling, and the per-step sine fit giving the frequency response H(f) = U_force / x with its
covariance.  Results go to the recording's ``/processed/steps`` with the settings used.

H(f) per step (V/(m/s^2)): the force-signal phasor divided by the frame-acceleration phasor, both
from the identification's sine fits (``station.ident.frf.step_response``: IEEE 1057 fits at the crank
frequency found by a four-parameter fit of the displacement, harmonics as nuisance terms), with the
2x2 covariance of its real and imaginary parts.  Zero-phase filtering acts identically on both channels,
so it cannot bias H; it only removes out-of-band noise before resampling.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import signal

from station.config import ProcessingConfig
from station.errors import StationError
from station.ident.frf import step_response as frf_step_response
from station.recording import Recording, read_recording, write_results

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


def condition(x: np.ndarray, fs: float, p: ProcessingConfig) -> tuple[np.ndarray, float]:
    """Zero-phase low-pass and polyphase resampling of one channel; returns (signal, new rate)."""
    y = x
    if p.lowpass_cutoff_hz < fs / 2:
        sos = signal.butter(p.lowpass_order, p.lowpass_cutoff_hz, fs=fs, output="sos")
        y = signal.sosfiltfilt(sos, y)
    if p.resample_up != p.resample_down:
        y = signal.resample_poly(y, p.resample_up, p.resample_down)
    return y, fs * p.resample_up / p.resample_down


def step_response(rec: Recording, index: int, p: ProcessingConfig) -> StepResponse:
    """Condition both channels of one step, then the identification's sine fits (frf.step_response)."""
    step = rec.steps[index]
    d, f = rec.step_signals(step)
    dd, fs2 = condition(d, rec.sample_rate_hz, p)
    ff, _ = condition(f, rec.sample_rate_hz, p)
    edge = int(0.02 * fs2)  # filter/resampler edge transients
    dd, ff = dd[edge:-edge or None], ff[edge:-edge or None]
    t = np.arange(dd.size) / fs2
    n_h = max(1, min(p.harmonics, int(0.45 * fs2 / step.crank_frequency_hz)))
    H, C, fx, fu = frf_step_response(t, dd, ff, step.crank_frequency_hz, n_harmonics=n_h)
    return StepResponse(index, fx.frequency_hz, fx.frequency_std_hz, complex(H), C, abs(fx.phasor),
                        abs(fu.phasor), fu.offset, fx.residual_rms, fu.residual_rms, dd.size)


def process_recording(path: str | Path, p: ProcessingConfig, rec: Recording | None = None) -> list[StepResponse]:
    """Fit every usable step of a complete recording and store the result in /processed/steps
    (``rec``: the recording already read from ``path``, to save reading it again)."""
    rec = rec if rec is not None else read_recording(path)
    if not rec.complete:
        raise StationError(f"{rec.path}: the recording is incomplete ({rec.reason}); recover it first")
    out, skipped = [], []
    for i, st in enumerate(rec.steps):
        if not st.usable:
            skipped.append({"step": i, "reason": f"{st.lost_in_window} samples lost in the record window"})
            continue
        out.append(step_response(rec, i, p))
    payload = {"settings": p.model_dump(), "skipped": skipped,
               "units": {"frequency_hz": "Hz", "H": "V/(m/s^2)", "H_cov": "(V/(m/s^2))^2",
                         "displacement_amplitude_m": "m", "force_amplitude_V": "V"},
               "steps": [{k: (v if not isinstance(v, complex) else [v.real, v.imag])
                          for k, v in asdict(s).items() if k != "H_cov"} for s in out]}
    arrays = {"frequency_hz": np.array([s.frequency_hz for s in out]),
              "H": np.array([s.H for s in out], dtype=complex),
              "H_cov": np.array([s.H_cov for s in out]).reshape(-1, 2, 2)}
    write_results(path, "steps", payload, arrays, group="processed")
    log.info("processed %d steps of %s (%d skipped)", len(out), rec.path.name, len(skipped))
    return out
