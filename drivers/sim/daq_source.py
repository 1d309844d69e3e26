"""Sample sources for the DAQ-bridge emulator: rig physics (RigSynth) or a plain sine for tests."""

from __future__ import annotations

import math
import threading
from dataclasses import replace
from typing import Protocol

import numpy as np

from drivers.rig.params import RigPhysics
from drivers.rig.synth import RigSynth


class SampleSource(Protocol):
    """Produces the next n samples of both channels while the crank frequency moves to f_end_hz."""

    def configure(self, rate_hz: float, range_disp_V: float, range_force_V: float) -> None:
        """Called at START with the bridge configuration (sample rate in Hz, ADC ranges +-V)."""

    def advance(self, n: int, f_end_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """(displacement int16[n], force int16[n]) ADC codes."""
        ...


class RigSource:
    """Both channels synthesised by the rig physics (:class:`RigSynth`), crank phase continuous.

    One synthesiser runs for as long as the configuration (rate, ranges) stays the same; the
    emulator keeps it running while idle, so the mechanics follow the motor between records.
    A new configuration starts a new synthesiser at standstill (a start-up transient if the
    crank is turning then).
    """

    def __init__(self, physics: RigPhysics, *, seed: int, crank_radius_m: float,
                 phi0_rad: float = 0.0) -> None:
        self.physics = physics
        self.seed = seed
        self.crank_radius_m = crank_radius_m
        self._phi0 = phi0_rad
        self._runs = 0
        self._key: tuple[float, float, float] | None = None
        self._lock = threading.Lock()
        self.synth: RigSynth | None = None

    _compiled = False  # the synthesis kernels compiled (or read from numba's cache) in this process

    def configure(self, rate_hz: float, range_disp_V: float, range_force_V: float) -> None:
        key = (rate_hz, range_disp_V, range_force_V)
        with self._lock:
            if self.synth is not None and key == self._key:
                return
            self._new_synth(key)
            self._compile_once()

    def warm(self) -> None:
        """The synthesis kernels compiled (or read from numba's cache) now: the emulators' process does
        it before it serves, so that the first configuration is answered within the station's 1 s."""
        with self._lock:
            self._compile_once()

    def _compile_once(self) -> None:
        """Synthesise a few samples on a throwaway synthesiser, once per process: the numba kernels are
        compiled (seconds on a fresh install, before their cache exists) at the first configuration,
        which the emulator makes before it answers, not at the first block synthesised while the
        station waits for a reply."""
        if RigSource._compiled:
            return
        physics = self.synth.physics if self.synth is not None else self.physics
        scratch = RigSynth(physics, seed=self.seed, crank_radius_m=self.crank_radius_m)
        scratch.advance(64, 1.0)  # kernels.synth_block: one signature for every effect set and crank profile
        RigSource._compiled = True

    def _new_synth(self, key: tuple[float, float, float]) -> None:
        rate_hz, range_disp_V, range_force_V = key
        phys = replace(self.physics, sample_rate_hz=rate_hz,
                       adc=replace(self.physics.adc, displacement_range_V=range_disp_V,
                                   force_range_V=range_force_V))
        phi0 = self.synth.crank_angle_rad if self.synth is not None else self._phi0
        self.synth = RigSynth(phys, seed=self.seed + self._runs, crank_radius_m=self.crank_radius_m,
                              phi0_rad=phi0)
        self._key = key
        self._runs += 1

    def set_phase(self, phi0_rad: float) -> None:
        """Crank angle (rad) for the next :meth:`configure` (from the motor emulator's angle)."""
        with self._lock:
            self._phi0 = phi0_rad
            self.synth = None

    def load(self, physics: RigPhysics) -> None:
        """Synthesise with other physics from now on (e.g. another top mass); the crank angle carries
        over to the next synthesiser.  The same physics again changes nothing."""
        with self._lock:
            if physics == self.physics:
                return
            if self.synth is not None:
                self._phi0 = float(self.synth.crank_angle_rad)
                self.synth = None
            self.physics = physics

    def set_crank_radius(self, radius_m: float) -> None:
        """Change the crank radius (m); only at standstill (RuntimeError otherwise)."""
        with self._lock:
            if self.synth is not None:
                self.synth.set_crank_radius(radius_m)
            self.crank_radius_m = radius_m

    def advance(self, n: int, f_end_hz: float) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            if self.synth is None and self._key is not None:
                # the physics or phase changed (set_phase) while the emulator keeps producing between
                # records: carry on with the last configuration, as its next CONF would
                self._new_synth(self._key)
            if self.synth is None:
                raise RuntimeError("RigSource.advance before configure")
            block = self.synth.advance(n, max(0.0, f_end_hz))
        return block.displacement_counts, block.force_counts


class SineSource:
    """A deterministic test source: displacement = A sin(phi), force = -A/2 sin(phi) (codes)."""

    def __init__(self, amplitude_counts: int = 12000) -> None:
        self.amplitude = amplitude_counts
        self.rate = 20_000.0
        self.phi = 0.0
        self.f = 0.0

    def configure(self, rate_hz: float, range_disp_V: float, range_force_V: float) -> None:
        self.rate = rate_hz

    def advance(self, n: int, f_end_hz: float) -> tuple[np.ndarray, np.ndarray]:
        f = self.f + (f_end_hz - self.f) * np.arange(1, n + 1) / n
        phi = self.phi + 2 * math.pi * np.cumsum(f) / self.rate
        self.phi, self.f = float(phi[-1] % (2 * math.pi)), f_end_hz
        s = np.sin(phi)
        return (self.amplitude * s).astype(np.int16), (-self.amplitude / 2 * s).astype(np.int16)
