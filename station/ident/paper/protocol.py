"""The paper's experiment protocol (Section 5.1) applied to one step of a recording.

"After filtering and resampling ... 200 input-output data points are taken for system
identification and another 400 data points are taken for testing."  The paper states neither
the filter nor the new rate; we low-pass and resample with ``scipy.signal.resample_poly`` to
``resample_hz`` (default 500 Hz), drop the filter's edge transients, take the frame acceleration
from Eq. 2 (a = -s w^2, w the crank angular frequency, s the displacement minus its mean) as the
input and the force signal minus its mean (the gravity preload) as the output.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from fractions import Fraction
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from station.errors import BadInputError
from station.recording import Recording, Step

if TYPE_CHECKING:
    from station.ident.paper.pso import PsoSettings

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PaperProtocol:
    """resample_hz: rate after resampling (Hz); n_identify / n_test: points (paper: 200 / 400);
    step_index: which step (None = the lowest-frequency usable one, the paper used 4 Hz);
    edge_s: seconds dropped at both ends after resampling (filter transients)."""

    resample_hz: float = 500.0
    n_identify: int = 200
    n_test: int = 400
    step_index: int | None = None
    edge_s: float = 0.05


@dataclass(frozen=True)
class SwarmSize:
    """A swarm size other than the published one (None: keep the settings' own; ``pso.PsoSettings``)."""

    n_particles: int | None = None
    n_iterations: int | None = None

    def applied(self, settings: PsoSettings) -> PsoSettings:
        return replace(settings, n_particles=self.n_particles or settings.n_particles,
                       n_iterations=self.n_iterations or settings.n_iterations)


PUBLISHED_SWARM = SwarmSize()  # the paper's own settings (Section 5.1)


@dataclass(frozen=True)
class PaperData:
    """Input (frame acceleration, m/s^2) and output (force signal, V) windows at rate 1/T (s)."""

    x_id: FloatArray
    y_id: FloatArray
    x_test: FloatArray
    y_test: FloatArray
    T: float
    f_hz: float
    step_index: int


def pick_step(rec: Recording, index: int | None) -> Step:
    """The requested step, or the lowest-frequency usable one."""
    usable = [s for s in rec.steps if s.usable]
    if not usable:
        raise BadInputError(f"{rec.path}: no usable step (samples lost in every record window)")
    if index is None:
        return min(usable, key=lambda s: s.crank_frequency_hz)
    for s in usable:
        if s.index == index:
            return s
    raise BadInputError(f"step {index} is not a usable step of {rec.path}")


def paper_data(rec: Recording, protocol: PaperProtocol = PaperProtocol()) -> PaperData:
    """Filter, resample and cut one step as in Section 5.1."""
    from scipy.signal import resample_poly  # here: the default identification needs no scipy.signal

    st = pick_step(rec, protocol.step_index)
    x, u = rec.step_signals(st)
    ratio = Fraction(protocol.resample_hz / rec.sample_rate_hz).limit_denominator(1000)
    xs = resample_poly(x - np.mean(x), ratio.numerator, ratio.denominator)
    us = resample_poly(u - np.mean(u), ratio.numerator, ratio.denominator)
    edge = round(protocol.edge_s * protocol.resample_hz)
    need = protocol.n_identify + protocol.n_test
    if xs.size - 2 * edge < need:
        raise BadInputError(f"step {st.index} gives {xs.size - 2 * edge} points at "
                            f"{protocol.resample_hz:g} Hz; the protocol needs {need}")
    w = 2 * np.pi * st.crank_frequency_hz
    a = -xs[edge:edge + need] * w**2  # Eq. 2
    y = us[edge:edge + need]
    n = protocol.n_identify
    return PaperData(a[:n], y[:n], a[n:], y[n:], 1.0 / protocol.resample_hz, st.crank_frequency_hz,
                     st.index)


def testing_mse(b: FloatArray, a: FloatArray, data: PaperData) -> float:
    """Testing MSE (Tables 2, 3): the identified model run on the test input from rest."""
    from scipy.signal import lfilter

    with np.errstate(all="ignore"):
        e = lfilter(b, a, data.x_test) - data.y_test
        v = float(np.mean(e**2))
    return v if np.isfinite(v) else float("inf")
