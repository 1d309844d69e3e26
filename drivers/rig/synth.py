"""Streaming synthesis of the two DAQ channels from the rig physics.

Signal chain per sample k (t_k = k / fs):
    crank angle phi(t) (frequency ramping linearly within a block) -> frame displacement x_b,
    acceleration, jerk (``crank``) -> mechanical chain (paper Eq. 3, exact Hermite discretisation)
    -> spring force F = k_f Z2 -> transducer output S*F*(1 + q F/C + c (F/C)^2) -> conditioner
    low-pass -> gain, offset, drift, mains, noise -> force ADC;
    x_b (sampled ``channel_delay`` earlier, and ``clock_skew`` t later) -> the displacement sensor's own resonance
    (``displacement_resonance``, a second-order low-pass integrated exactly like the mechanics)
    -> displacement sensor gain + noise -> displacement ADC.

Every effect is off unless configured (``params.Effects``).  Blocks may have any length; the
result does not depend on how a run is cut into blocks (the noise of sample k is draw k of its
channel's counter-based stream, ``kernels.standard_normal``, keyed by the seed).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.rig import crank
from drivers.rig.discretize import FilterBank, hermite_discretize
from drivers.rig.model import lowpass_state_space, mechanical_state_space, sensor_resonance_state_space
from drivers.rig.params import Effects, MainsInterference, RigPhysics


@dataclass(frozen=True)
class SynthBlock:
    """One block of synthesised samples, all arrays of shape (n,).

    start_sample: index of the first sample since the synthesiser started;
    displacement_counts, force_counts: ADC codes (int16);
    displacement_V, force_V: analogue ADC inputs in V (noise included, before quantisation);
    displacement_m: true frame displacement in m; crank_frequency_hz: crank frequency at each sample;
    clipped: number of samples (both channels) that hit the ADC range.
    """

    start_sample: int
    displacement_counts: np.ndarray
    force_counts: np.ndarray
    displacement_V: np.ndarray
    force_V: np.ndarray
    displacement_m: np.ndarray
    crank_frequency_hz: np.ndarray
    clipped: int


class RigSynth:
    """Synthesises the DAQ channels block by block, carrying every state exactly between blocks."""

    def __init__(self, physics: RigPhysics, *, seed: int, crank_radius_m: float,
                 phi0_rad: float = 0.0) -> None:
        """Start at standstill in the gravity equilibrium, crank at ``phi0_rad``."""
        self.physics = physics
        self._T = 1.0 / physics.sample_rate_hz
        self._phi = float(phi0_rad)
        self._f = 0.0
        self._k = 0
        self._radius = 0.0
        self.set_crank_radius(crank_radius_m)
        eff = physics.effects
        g = physics.gravity_m_per_s2
        self._need_rate = eff.conditioner_lowpass is not None
        mech = hermite_discretize(mechanical_state_space(physics.transducer, eff.coupling_compliance),
                                  self._T)
        self._mech = FilterBank(mech, u0=g, outputs=2 if self._need_rate else 1)
        self._lowpass: FilterBank | None = None
        if eff.conditioner_lowpass is not None:
            F0 = -physics.transducer.total_mass_kg * g
            lp = hermite_discretize(lowpass_state_space(eff.conditioner_lowpass), self._T)
            self._lowpass = FilterBank(lp, u0=float(self._transducer_output(np.array([F0]))[0]))
        self._sensor: FilterBank | None = None
        if eff.displacement_resonance is not None:
            x0 = crank.displacement_at_angle(self._coeffs, self._phi)
            self._sensor = FilterBank(hermite_discretize(sensor_resonance_state_space(eff.displacement_resonance),
                                                         self._T), u0=x0)
        self._mech_coefficients = self._mech.coefficients
        self._lp_coefficients = (self._lowpass or _NO_FILTER).coefficients
        self._sensor_coefficients = (self._sensor or _NO_FILTER).coefficients
        self._mains_weights = (_mains_weights(eff.mains_interference) if eff.mains_interference is not None
                               else np.zeros((1, 2)))
        self._tables: dict[float, np.ndarray] = {}
        self._steady_freq = np.broadcast_to(0.0, (0,))
        self._fl, self._ints = self._kernel_arguments()
        disp_seq, force_seq = np.random.SeedSequence(seed).spawn(2)
        # the keys of the force's and the displacement's noise streams (``kernels.standard_normal``)
        self._noise_keys = np.concatenate([s.generate_state(1, np.uint64) for s in (force_seq, disp_seq)])

    def _kernel_arguments(self) -> tuple[np.ndarray, np.ndarray]:
        """``kernels.synth_block``'s fl and ints with what stays the same from block to block; each
        block fills in its own (f0, rate, alpha, cd, sd, centre; n, the sample index, ramp, shift mode)."""
        ph = self.physics
        eff, t, cond, sens, adc = ph.effects, ph.transducer, ph.conditioner, ph.displacement_sensor, ph.adc
        nl, drift = eff.transducer_nonlinearity, eff.zero_drift
        lo, hi = -(2 ** (adc.bits - 1)), 2 ** (adc.bits - 1) - 1
        fl = np.array([
            self._T, 0.0, 0.0, 0.0, ph.gravity_m_per_s2,
            t.sensitivity_V_per_N, t.capacity_N, nl.quadratic if nl else 0.0, nl.cubic if nl else 0.0,
            cond.gain, cond.offset_V, drift.rate_V_per_s if drift else 0.0,
            drift.quadratic_V_per_s2 if drift else 0.0, cond.noise_V,
            1.0, 0.0, eff.channel_delay.delay_s if eff.channel_delay else 0.0,
            eff.clock_skew.relative if eff.clock_skew else 0.0,
            sens.gain_V_per_m, sens.noise_m * sens.gain_V_per_m,
            adc.volts_per_count(adc.displacement_range_V), adc.volts_per_count(adc.force_range_V), lo, hi, 0.0,
        ], dtype=float)
        ints = np.array([
            0, 0, 0, nl is not None, self._lowpass is not None, drift is not None,
            eff.mains_interference is not None, cond.noise_V > 0, 0, self._sensor is not None,
            sens.noise_m > 0,
        ], dtype=np.int64)
        return fl, ints

    # -- state -------------------------------------------------------------------------------
    @property
    def crank_frequency_hz(self) -> float:
        """Crank frequency at the next sample, Hz."""
        return self._f

    @property
    def crank_angle_rad(self) -> float:
        """Crank angle at the next sample, rad in [0, 2*pi)."""
        return self._phi

    @property
    def crank_radius_m(self) -> float:
        return self._radius

    @property
    def sample_index(self) -> int:
        """Index of the next sample to be synthesised."""
        return self._k

    def set_crank_radius(self, radius_m: float) -> None:
        """Change the crank radius (m); only at standstill, as on the real rig."""
        if self._f != 0.0:
            raise RuntimeError(f"the crank radius can only change at standstill (crank at {self._f} Hz)")
        if not radius_m >= 0.0:
            raise ValueError(f"crank radius must be >= 0 m, got {radius_m}")
        self._radius = float(radius_m)
        self._coeffs = crank.displacement_coefficients(self._radius, self.physics.effects.crank_harmonics)
        self._weights = crank.harmonic_weights(self._coeffs)

    # -- synthesis -----------------------------------------------------------------------------
    def _transducer_output(self, F: np.ndarray) -> np.ndarray:
        """Transducer output in V for spring force F in N (with the nonlinearity if switched on)."""
        t = self.physics.transducer
        nl = self.physics.effects.transducer_nonlinearity
        if nl is None:
            return t.sensitivity_V_per_N * F
        x = F / t.capacity_N
        return t.sensitivity_V_per_N * F * (1.0 + nl.quadratic * x + nl.cubic * x * x)

    def _transducer_output_rate(self, F: np.ndarray, dF: np.ndarray) -> np.ndarray:
        t = self.physics.transducer
        nl = self.physics.effects.transducer_nonlinearity
        if nl is None:
            return t.sensitivity_V_per_N * dF
        x = F / t.capacity_N
        return t.sensitivity_V_per_N * dF * (1.0 + 2.0 * nl.quadratic * x + 3.0 * nl.cubic * x * x)

    def advance(self, n: int, f_end_hz: float) -> SynthBlock:
        """Synthesise the next n samples while the crank frequency moves linearly to f_end_hz.

        Every stage in one compiled pass (``kernels.synth_block``): the same samples to the bit as
        ``advance_stages``."""
        self._check(n, f_end_hz)
        from drivers.rig import kernels  # numba: imported (and compiled or read from its cache) on first use

        ph, T = self.physics, self._T
        eff = ph.effects
        f0 = self._f
        rate = (f_end_hz - f0) / (n * T)  # Hz/s
        alpha = 2.0 * np.pi * rate
        dphi, c2 = 2.0 * np.pi * f0 * T, np.pi * rate * T * T
        if c2 != 0.0:
            crank_cs = np.stack(crank.cos_sin(self._phi, dphi, c2, n))
            crank_base, crank_tab = _NO_ROTATION
        else:
            crank_cs = _NO_SAMPLES2
            crank_base, crank_tab = crank.rotation_base(self._phi, dphi, n), self._table(dphi)
        if eff.mains_interference is not None:
            w = 2.0 * np.pi * eff.mains_interference.frequency_hz
            mains_base, mains_tab = crank.rotation_base(w * (self._k * T), w * T, n), self._table(w * T)
        else:
            mains_base, mains_tab = _NO_ROTATION
        shift_mode, cd, sd, shift_cs, centre = self._shift(n, f0, f_end_hz, rate, alpha)
        fl, ints = self._fl.copy(), self._ints.copy()
        fl[1], fl[2], fl[3], fl[14], fl[15], fl[24] = f0, rate, alpha, cd, sd, centre
        ints[0], ints[1], ints[2], ints[8] = n, self._k, c2 != 0.0, shift_mode
        x, force_V, disp_V = np.empty(n), np.empty(n), np.empty(n)
        dc, fc = np.empty(n, dtype=np.int16), np.empty(n, dtype=np.int16)
        lp, sensor = self._lowpass or _NO_FILTER, self._sensor or _NO_FILTER
        clipped = kernels.synth_block(
            fl, ints, crank_base, crank_tab, crank_cs, self._weights, self._mech_coefficients, self._mech.state,
            self._lp_coefficients, lp.state, mains_base, mains_tab, self._mains_weights, self._noise_keys,
            shift_cs, self._sensor_coefficients, sensor.state, x, force_V, disp_V, dc, fc)
        return self._finish(n, f_end_hz, SynthBlock(
            start_sample=self._k, displacement_counts=dc, force_counts=fc, displacement_V=disp_V,
            force_V=force_V, displacement_m=x, crank_frequency_hz=self._frequencies(n, f0, rate),
            clipped=int(clipped)))

    def _frequencies(self, n: int, f0: float, rate: float) -> np.ndarray:
        """The crank frequency (Hz) at the block's n samples; a steady block's is one read-only view,
        kept while blocks repeat it."""
        if rate != 0.0:
            return f0 + rate * (np.arange(n) * self._T)
        if self._steady_freq.shape != (n,) or self._steady_freq[0] != f0:
            self._steady_freq = np.broadcast_to(f0, (n,))
        return self._steady_freq

    def _table(self, dphi: float) -> np.ndarray:
        """``crank.rotation_table(dphi)``, kept for the few steps (crank frequencies) a run repeats."""
        table = self._tables.get(dphi)
        if table is None:
            if len(self._tables) >= 16:
                self._tables.clear()
            table = self._tables[dphi] = crank.rotation_table(dphi)
        return table

    def _shift(self, n: int, f0: float, f_end: float, rate: float,
               alpha: float) -> tuple[int, float, float, np.ndarray, float]:
        """How ``kernels.synth_block`` lags the displacement channel's crank angle in this block:
        (mode, cos, sin, given (2, n), centre); 0 no lag, 1 one constant lag (its cos, sin), 2 the
        per-sample Taylor series of ``crank.shift_cos_sin`` (every lag certainly below its 0.1 rad),
        4 a constant lag ``centre`` (rad; its cos, sin) and the Taylor series of the per-sample lag
        less it (a clock skew's lag grown large over a run, every lag within 0.1 rad of the centre),
        3 given per sample."""
        eff, T = self.physics.effects, self._T
        if eff.channel_delay is None and eff.clock_skew is None:
            return 0, 1.0, 0.0, _NO_SAMPLES2, 0.0
        if eff.clock_skew is None and rate == 0.0:
            omega, d = 2.0 * np.pi * f0, eff.channel_delay.delay_s if eff.channel_delay else 0.0
            cd, sd = crank.shift_cos_sin(omega * d - 0.5 * alpha * d * d)
            return 1, float(cd), float(sd), _NO_SAMPLES2, 0.0
        # |delta| <= |omega| |d| + |alpha| d^2 / 2, d linear in t: its largest at either end
        d_ends = (float(_displacement_lag(eff, self._k * T)), float(_displacement_lag(eff, (self._k + n - 1) * T)))
        d_max = max(abs(d_ends[0]), abs(d_ends[1]))
        if 2.0 * np.pi * max(f0, f_end) * d_max + 0.5 * abs(alpha) * d_max * d_max < 0.099:
            return 2, 1.0, 0.0, _NO_SAMPLES2, 0.0
        lo, hi = self._lag_range(n, f0, rate, alpha)
        if hi - lo < 0.198:
            centre = 0.5 * (lo + hi)
            cd, sd = crank.shift_cos_sin(centre)
            return 4, float(cd), float(sd), _NO_SAMPLES2, centre
        cd_k, sd_k = crank.shift_cos_sin(self._lag_angle(np.arange(n), f0, rate, alpha))
        return 3, 1.0, 0.0, np.stack(np.broadcast_arrays(cd_k, sd_k)).astype(float), 0.0

    def _lag_angle(self, k: np.ndarray, f0: float, rate: float, alpha: float) -> np.ndarray:
        """The displacement channel's lag behind the crank (rad) at the block's samples k (shape (m,))."""
        d = _displacement_lag(self.physics.effects, (self._k + k) * self._T)
        return 2.0 * np.pi * (f0 + rate * (k * self._T)) * d - 0.5 * alpha * d * d

    def _lag_range(self, n: int, f0: float, rate: float, alpha: float) -> tuple[float, float]:
        """The smallest and largest lag (rad) over the block's n samples: the lag is quadratic in the
        sample index (the crank rate and the lag time both linear in it), so at either end or its vertex."""
        eff, T, k_abs = self.physics.effects, self._T, self._k

        def lag(k: float) -> float:
            d = float(_displacement_lag(eff, (k_abs + k) * T))
            return 2.0 * np.pi * (f0 + rate * (k * T)) * d - 0.5 * alpha * d * d

        h = 0.5 * (n - 1)
        d0, d1, d2 = lag(0.0), lag(h), lag(n - 1.0)
        lags = [d0, d2]
        curve = d0 - 2.0 * d1 + d2
        if h > 0.0 and curve != 0.0:
            vertex = h - h * (d2 - d0) / (2.0 * curve)
            if 0.0 < vertex < n - 1.0:
                lags.append(lag(vertex))
        return min(lags), max(lags)

    def advance_stages(self, n: int, f_end_hz: float) -> SynthBlock:
        """``advance`` stage by stage in numpy with the compiled harmonic sums and filter bank (the
        synthesis as it was before ``kernels.synth_block``, its noise drawn as the one pass draws it):
        slower; the definition the one-pass kernel is tested against and the baseline
        ``bench/simulate.py`` measures it beside.
        Interchangeable with ``advance`` block by block (the same states)."""
        self._check(n, f_end_hz)
        ph, T = self.physics, self._T
        eff = ph.effects
        f0 = self._f
        rate = (f_end_hz - f0) / (n * T)  # Hz/s
        if rate == 0.0:
            freq: np.ndarray | float = f0
        else:
            freq = f0 + rate * (np.arange(n) * T)
        omega = 2.0 * np.pi * freq
        alpha = 2.0 * np.pi * rate
        # phi_k = phi + 2 pi (f0 k T + rate (k T)^2 / 2)
        cs = crank.cos_sin(self._phi, 2.0 * np.pi * f0 * T, np.pi * rate * T * T, n)
        kin = crank.evaluate(self._coeffs, cs, omega, alpha)

        u = kin.acceleration + ph.gravity_m_per_s2
        mech = self._mech.run(u, kin.jerk)
        v = self._transducer_output(mech[0])
        if self._lowpass is not None:
            v = self._lowpass.run(v, self._transducer_output_rate(mech[0], mech[1]))[0]
        cond = ph.conditioner
        force_V = cond.gain * v + cond.offset_V
        if eff.zero_drift is not None:
            t_abs = (self._k + np.arange(n)) * T
            force_V += eff.zero_drift.rate_V_per_s * t_abs + eff.zero_drift.quadratic_V_per_s2 * t_abs**2
        if eff.mains_interference is not None:
            force_V += _mains(eff.mains_interference, self._k * T, T, n)
        if cond.noise_V > 0:
            force_V += self._noise(0, n) * cond.noise_V

        x = kin.displacement
        cs_x = cs
        if eff.channel_delay is not None or eff.clock_skew is not None:
            d = _displacement_lag(eff, (self._k + np.arange(n)) * T)
            delta = omega * d - 0.5 * alpha * d * d
            mode, _, _, _, centre = self._shift(n, f0, f_end_hz, rate, alpha)
            if mode == 4:  # the constant lag, then what is left of each sample's
                cs_x = crank.shift_angle(crank.shift_angle(cs, centre), delta - centre)
            else:
                cs_x = crank.shift_angle(cs, delta)
            x = crank.displacement_at(self._coeffs, cs_x)
        if self._sensor is not None:
            x, dx_dphi = crank.displacement_and_slope(self._coeffs, cs_x)
            x = self._sensor.run(x, dx_dphi * omega)[0]
        sens = ph.displacement_sensor
        disp_V = sens.gain_V_per_m * x
        if sens.noise_m > 0:
            disp_V += self._noise(1, n) * (sens.noise_m * sens.gain_V_per_m)

        dc, clip_d = _quantise(disp_V, ph.adc.volts_per_count(ph.adc.displacement_range_V), ph.adc.bits)
        fc, clip_f = _quantise(force_V, ph.adc.volts_per_count(ph.adc.force_range_V), ph.adc.bits)
        return self._finish(n, f_end_hz, SynthBlock(
            start_sample=self._k, displacement_counts=dc, force_counts=fc, displacement_V=disp_V,
            force_V=force_V, displacement_m=kin.displacement, crank_frequency_hz=np.broadcast_to(freq, (n,)),
            clipped=clip_d + clip_f))

    def _noise(self, channel: int, n: int) -> np.ndarray:
        """The standard normal draws of the block's n samples for channel 0 (force) or 1 (displacement)."""
        from drivers.rig import kernels  # numba: imported (and compiled or read from its cache) on first use

        out = np.empty(n)
        kernels.fill_standard_normal(self._noise_keys[channel], self._k, out)
        return out

    @staticmethod
    def _check(n: int, f_end_hz: float) -> None:
        if n <= 0:
            raise ValueError(f"block length must be positive, got {n}")
        if f_end_hz < 0.0:
            raise ValueError(f"crank frequency must be >= 0 Hz, got {f_end_hz}")

    def _finish(self, n: int, f_end_hz: float, block: SynthBlock) -> SynthBlock:
        """Move the crank angle, frequency and sample index past the block just synthesised."""
        f0 = self._f
        self._phi = float(np.mod(self._phi + 2.0 * np.pi * n * self._T * (f0 + f_end_hz) / 2.0, 2.0 * np.pi))
        self._f = float(f_end_hz)
        self._k += n
        return block


def _displacement_lag(eff: Effects, t: np.ndarray | float) -> np.ndarray | float:
    """How long before the force sample at t (s, shape (n,) or a scalar) the displacement sample is taken, s:
    the channel delay, less the clock skew's growing lead (``params.ClockSkew``)."""
    d: np.ndarray | float = eff.channel_delay.delay_s if eff.channel_delay is not None else 0.0
    if eff.clock_skew is not None:
        d = d - eff.clock_skew.relative * t
    return d


def _mains(m: MainsInterference, t0: float, T: float, n: int) -> np.ndarray:
    """Mains pick-up in V at the n sample instants t0 + k T (s)."""
    w = 2.0 * np.pi * m.frequency_hz
    pickup: np.ndarray = crank.harmonic_sum(crank.cos_sin(w * t0, w * T, 0.0, n), _mains_weights(m))[0]
    return pickup


def _mains_weights(m: MainsInterference) -> np.ndarray:
    """The mains pick-up as ``crank.harmonic_sum`` weights (1, 2K) of cos(h w t), sin(h w t)."""
    k = len(m.amplitudes_V)
    amp = np.asarray(m.amplitudes_V)
    ph = np.array([m.phases_rad[h] if h < len(m.phases_rad) else 0.0 for h in range(k)])
    # sum_h A_h sin(h w t + ph_h) = sum_h A_h (sin(h w t) cos ph_h + cos(h w t) sin ph_h)
    return np.concatenate([amp * np.sin(ph), amp * np.cos(ph)])[None, :]


_NO_SAMPLES2 = np.empty((2, 0))
_NO_ROTATION = (np.empty((2, 0)), np.empty((2, 0)))


class _NoFilter:
    """The coefficients and state ``kernels.synth_block`` takes for a filter that is switched off."""

    coefficients = np.array([[[0.0, 0.0]], [[0.0, 0.0]], [[1.0, 0.0]]])
    state = np.zeros((1, 1))


_NO_FILTER = _NoFilter()


def _quantise(v: np.ndarray, lsb: float, bits: int) -> tuple[np.ndarray, int]:
    """ADC codes for voltages v with code size lsb (V); returns (int16 codes, clipped count)."""
    lo, hi = -(2 ** (bits - 1)), 2 ** (bits - 1) - 1
    codes = np.rint(v / lsb)
    clipped = int(np.count_nonzero((codes < lo) | (codes > hi)))
    np.clip(codes, lo, hi, out=codes)
    return codes.astype(np.int16), clipped
