"""Physical parameters of the simulated sine-mechanism rig (SI units throughout).

These frozen dataclasses are the *only* vocabulary the simulator speaks, and the effect catalogue
(``Effects``) is declared only here: each field's valid range is part of its type
(``annotated_types`` bounds), and the station's configuration validates ``simulation.effects``
straight into these classes (``station.config``), so the ``drivers`` layer never imports ``station``.

Model (paper Eq. 3, frame/base motion prescribed by the crank):

    m_l x_l'' = -k_c (x_l - x_e) - b_c (x_l' - x_e') - m_l g
    m_e x_e'' =  k_c (x_l - x_e) + b_c (x_l' - x_e') - k_f (x_e - x_b) - b_f (x_e' - x_b') - m_e g

with x_b(t) the frame displacement.  The force transducer's signal is proportional to its
deformation Z2 = x_e - x_b (strain gauges), scaled so that in the static limit it reads the spring
force ``k_f * Z2`` times the sensitivity: ``U = S * k_f * Z2``.  In the static limit
``k_f Z2 = -(m_e + m_l)(a + g)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Annotated, Any

from annotated_types import Ge, Gt, Le, MaxLen, MinLen

G_STANDARD = 9.80665  # m/s^2


@dataclass(frozen=True)
class Transducer:
    """Mechanical model of the force transducer with its load.

    k_f: transducer stiffness in N/m; b_f: transducer damping in N*s/m;
    m_e: end mass in kg; m_l: load mass (top mass + adaption) in kg;
    sensitivity_V_per_N: transducer (bridge) output per newton of spring force, in V/N.
    """

    k_f: float
    b_f: float
    m_e: float
    m_l: float
    sensitivity_V_per_N: float
    capacity_N: float = float("inf")

    @property
    def total_mass_kg(self) -> float:
        return self.m_e + self.m_l


@dataclass(frozen=True)
class CouplingCompliance:
    """Finite coupling between load mass and transducer (paper Eq. 8): k_c in N/m, b_c in N*s/m."""

    k_c: Annotated[float, Gt(0), Le(1e13)]
    b_c: Annotated[float, Ge(0), Le(1e8)]


@dataclass(frozen=True)
class ConditionerLowpass:
    """Analogue Butterworth low-pass in the signal conditioner: order, cut-off (-3 dB) in Hz."""

    order: Annotated[int, Ge(1), Le(8)]
    cutoff_hz: Annotated[float, Gt(0), Le(100_000)]


@dataclass(frozen=True)
class ChannelDelay:
    """Time skew of a multiplexed ADC: the force sample k is taken ``delay_s`` seconds after the
    displacement sample k (positive delay).  Force/displacement phase changes by +2*pi*f*delay_s."""

    delay_s: Annotated[float, Ge(-1e-3), Le(1e-3)]


@dataclass(frozen=True)
class ClockSkew:
    """The two converters on clocks of their own: the force converter's runs ``relative`` fast against
    the displacement converter's (its sample k comes at k T / (1 + relative)).  On the force's time
    base the displacement sample k is taken at t_k (1 + relative): a force/displacement phase that
    grows with time, within a step and from step to step (+2*pi*f*relative*t)."""

    relative: Annotated[float, Ge(-1e-3), Le(1e-3)]


@dataclass(frozen=True)
class CrankHarmonics:
    """Non-sinusoidal frame motion of a slider-crank with a connecting rod of ``rod_length_m``.

    x_b(phi) = r sin(phi) + sqrt(L^2 - r^2 cos^2 phi) - mean; second-harmonic amplitude ~ r^2/(4L).
    """

    rod_length_m: Annotated[float, Gt(0), Le(10)]


@dataclass(frozen=True)
class TransducerNonlinearity:
    """Sensitivity that depends on the force: U = S*F*(1 + quadratic*(F/C) + cubic*(F/C)^2),
    F the spring force in N (preload included), C the capacity in N; coefficients dimensionless."""

    quadratic: Annotated[float, Ge(-0.5), Le(0.5)]
    cubic: Annotated[float, Ge(-0.5), Le(0.5)] = 0.0


@dataclass(frozen=True)
class MainsInterference:
    """Mains pick-up on the force channel (conditioner output): amplitudes in V of the fundamental
    and its harmonics (index 0 = mains frequency), phases in rad."""

    amplitudes_V: Annotated[tuple[float, ...], MinLen(1), MaxLen(10)]
    frequency_hz: Annotated[float, Ge(45), Le(65)] = 50.0
    phases_rad: Annotated[tuple[float, ...], MaxLen(10)] = ()


@dataclass(frozen=True)
class ZeroDrift:
    """Slow offset drift of the conditioner output: offset(t) = rate_V_per_s * t + quadratic_V_per_s2 * t^2."""

    rate_V_per_s: Annotated[float, Ge(-1), Le(1)]
    quadratic_V_per_s2: Annotated[float, Ge(-1), Le(1)] = 0.0


@dataclass(frozen=True)
class DisplacementResonance:
    """The displacement sensor's own second-order resonance (e.g. a seismic or capacitive pick-up on
    its mount): the measured frame displacement is x_m = H_s x_b with

        H_s(j w) = w_r^2 / (w_r^2 - w^2 + 2 j p w_r w),   w_r = 2 pi resonance_hz,

    damping p the damping ratio (dimensionless).  Flat (1) far below the resonance: +(f/f_r)^2
    (1 - 2 p^2) in gain and -2 p f/f_r rad in phase to first order.  ``response`` is the one
    definition the simulator and the station's measurement chain both use."""

    resonance_hz: Annotated[float, Gt(0), Le(1e6)]
    damping: Annotated[float, Ge(0), Le(10)] = 0.0

    def response(self, f_hz: Any) -> Any:
        """H_s at f_hz (Hz, scalar or array): measured over true displacement, complex."""
        import numpy as np

        r = np.asarray(f_hz, dtype=float) / self.resonance_hz
        return 1.0 / (1.0 - r * r + 2j * self.damping * r)


@dataclass(frozen=True)
class TransducerAgeing:
    """The transducer's slow change between calibrations: from ``onset_day`` on, its sensitivity and
    its stiffness k_f change by the relative rates per day (1/d) of the rig's clock, counted from when
    the rig was built: S(t) = S (1 + sensitivity_per_day (t - onset)), likewise k_f.  A run synthesises
    the values at the moment it is loaded; within one run (minutes) a drift of 0.1 %/month moves S by
    about 2e-8 of itself, so the run sees constant values.  Not an effect within a run: the discrepancy
    fits cannot see it, the control charts over runs do."""

    sensitivity_per_day: Annotated[float, Ge(-0.01), Le(0.01)] = 0.0
    k_f_per_day: Annotated[float, Ge(-0.01), Le(0.01)] = 0.0
    onset_day: Annotated[float, Ge(0), Le(36_500)] = 0.0

    def factors(self, age_days: float) -> tuple[float, float]:
        """(S, k_f) relative to the nominal ones at ``age_days`` days after the rig was built."""
        t = max(0.0, age_days - self.onset_day)
        return 1.0 + self.sensitivity_per_day * t, 1.0 + self.k_f_per_day * t


@dataclass(frozen=True)
class Effects:
    """The catalogue of effects; each is off (None) by default and they compose freely."""

    coupling_compliance: CouplingCompliance | None = None
    conditioner_lowpass: ConditionerLowpass | None = None
    channel_delay: ChannelDelay | None = None
    crank_harmonics: CrankHarmonics | None = None
    transducer_nonlinearity: TransducerNonlinearity | None = None
    mains_interference: MainsInterference | None = None
    zero_drift: ZeroDrift | None = None
    displacement_resonance: DisplacementResonance | None = None
    clock_skew: ClockSkew | None = None
    ageing: TransducerAgeing | None = None

    def active(self) -> list[str]:
        """Names of the effects that are switched on."""
        return [name for name in EFFECT_NAMES if getattr(self, name) is not None]


EFFECT_NAMES: tuple[str, ...] = (
    "coupling_compliance",
    "conditioner_lowpass",
    "channel_delay",
    "crank_harmonics",
    "transducer_nonlinearity",
    "mains_interference",
    "zero_drift",
    "displacement_resonance",
    "clock_skew",
    "ageing",
)


@dataclass(frozen=True)
class DisplacementSensor:
    """Displacement transducer on the frame: gain in V/m, white noise in m RMS (at the sample rate)."""

    gain_V_per_m: float
    noise_m: float = 0.0


@dataclass(frozen=True)
class Conditioner:
    """Signal conditioner of the force channel: gain in V/V, output offset in V, white noise in V RMS."""

    gain: float = 1.0
    offset_V: float = 0.0
    noise_V: float = 0.0


@dataclass(frozen=True)
class Adc:
    """Two-channel ADC: resolution in bits, symmetric input ranges in V (+-range), clipping at range."""

    bits: int = 16
    displacement_range_V: float = 10.0
    force_range_V: float = 10.0

    def volts_per_count(self, range_V: float) -> float:
        """Size of one code in V for a symmetric range of +-range_V."""
        codes: int = 2**self.bits
        return 2.0 * range_V / codes


@dataclass(frozen=True)
class RigPhysics:
    """Everything the simulator needs to synthesise both channels."""

    transducer: Transducer
    displacement_sensor: DisplacementSensor
    conditioner: Conditioner
    adc: Adc = field(default_factory=Adc)
    effects: Effects = field(default_factory=Effects)
    gravity_m_per_s2: float = G_STANDARD
    sample_rate_hz: float = 20_000.0

    def aged(self, age_days: float) -> RigPhysics:
        """These physics ``age_days`` days after the rig was built (``effects.ageing``; itself without it)."""
        ageing = self.effects.ageing
        if ageing is None:
            return self
        fs, fk = ageing.factors(age_days)
        t = self.transducer
        return replace(self, transducer=replace(t, sensitivity_V_per_N=t.sensitivity_V_per_N * fs, k_f=t.k_f * fk))
