"""Steady state of a running step: both signals' amplitudes and the crank's frequency agree over
consecutive windows (the run records a step only then).  Pure functions of the samples, used
wherever the samples are (``stream.LocalStream``, next to the acquisition's ring buffer)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from station.ident.response.sinefit import fit3, fit4


@dataclass(frozen=True)
class SteadyCriteria:
    """Steady state: amplitudes of both channels over consecutive windows agree within
    ``amplitude_tol`` (relative), the fitted crank frequency is within ``frequency_tol_hz`` of the
    setpoint (or 0.2 % of it, whichever is larger), for ``windows`` windows of ``window_s`` seconds."""

    amplitude_tol: float = 0.005
    frequency_tol_hz: float = 0.02
    window_s: float = 0.25
    windows: int = 3
    timeout_s: float = 20.0

    def samples(self, fs: float) -> int:
        """Samples the check reads at ``fs`` Hz (every window's)."""
        return int(self.window_s * fs) * self.windows

    def to_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SteadyCriteria:
        """The criteria as ``to_dict`` gave them (ValueError for a value out of its range)."""
        crit = cls(float(d["amplitude_tol"]), float(d["frequency_tol_hz"]), float(d["window_s"]),
                   int(d["windows"]), float(d["timeout_s"]))
        if not (0 < crit.amplitude_tol < 1 and crit.frequency_tol_hz > 0 and 0.01 <= crit.window_s <= 10
                and 1 <= crit.windows <= 20):
            raise ValueError(f"steadiness criteria out of range: {crit}")
        return crit


def is_steady(disp: np.ndarray, force: np.ndarray, f_set: float, fs: float, crit: SteadyCriteria) -> bool:
    """Apply ``crit`` to the newest samples (each channel: windows * window_s seconds)."""
    n = int(crit.window_s * fs)
    t = np.arange(n) / fs
    amps_d, amps_f, freqs = [], [], []
    for k in range(crit.windows):
        sl = slice(k * n, (k + 1) * n)
        fd = fit4(t, disp[sl].astype(float), f_set, max_iter=5)
        ff = fit3(t, force[sl].astype(float), fd.frequency_hz)
        amps_d.append(abs(fd.phasor))
        amps_f.append(abs(ff.phasor))
        freqs.append(fd.frequency_hz)
    tol_f = max(crit.frequency_tol_hz, 0.002 * f_set)
    if any(abs(f - f_set) > tol_f for f in freqs) or min(amps_d) <= 0 or min(amps_f) <= 0:
        return False
    return (max(amps_d) / min(amps_d) - 1 < crit.amplitude_tol
            and max(amps_f) / min(amps_f) - 1 < crit.amplitude_tol)
