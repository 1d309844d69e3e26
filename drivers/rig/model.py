"""Continuous-time models of the rig: paper Eq. 3 as state space, and analytic frequency responses.

Input of the mechanical stage is the *total* frame acceleration u = x_b'' + g (m/s^2), i.e. the
paper's X_b'' (Sec. 2.1.1).  Outputs are the transducer spring force F = k_f*Z2 (N) and its rate
F' = k_f*Z2' (N/s).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.rig.params import (
    ConditionerLowpass,
    CouplingCompliance,
    DisplacementResonance,
    RigPhysics,
    Transducer,
)


@dataclass(frozen=True)
class StateSpace:
    """x' = A x + B u, y = C x (no feed-through).  A: (n, n), B: (n, 1), C: (p, n)."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray


def mechanical_state_space(t: Transducer, coupling: CouplingCompliance | None) -> StateSpace:
    """State space of the transducer chain with the frame motion prescribed.

    Stiff coupling (Eq. 9), state [Z2, Z2']:  M Z2'' = -k_f Z2 - b_f Z2' - M u,  M = m_e + m_l.
    Finite coupling (Eq. 8), state [Z1, Z1', Z2, Z2'] with Z1 = x_l - x_e:
        Z2'' = (k_c Z1 + b_c Z1' - k_f Z2 - b_f Z2')/m_e - u
        Z1'' = -(k_c Z1 + b_c Z1')(1/m_l + 1/m_e) + (k_f Z2 + b_f Z2')/m_e
    Outputs: [k_f Z2, k_f Z2'] in N and N/s.
    """
    if coupling is None:
        M = t.total_mass_kg
        A = np.array([[0.0, 1.0], [-t.k_f / M, -t.b_f / M]])
        B = np.array([[0.0], [-1.0]])
        C = np.array([[t.k_f, 0.0], [0.0, t.k_f]])
        return StateSpace(A, B, C)
    kc, bc = coupling.k_c, coupling.b_c
    inv_u1 = 1.0 / t.m_l + 1.0 / t.m_e
    A = np.array(
        [
            [0.0, 1.0, 0.0, 0.0],
            [-kc * inv_u1, -bc * inv_u1, t.k_f / t.m_e, t.b_f / t.m_e],
            [0.0, 0.0, 0.0, 1.0],
            [kc / t.m_e, bc / t.m_e, -t.k_f / t.m_e, -t.b_f / t.m_e],
        ]
    )
    B = np.array([[0.0], [0.0], [0.0], [-1.0]])
    C = np.array([[0.0, 0.0, t.k_f, 0.0], [0.0, 0.0, 0.0, t.k_f]])
    return StateSpace(A, B, C)


def lowpass_state_space(lp: ConditionerLowpass) -> StateSpace:
    """Analogue Butterworth low-pass of the conditioner (unit DC gain), as state space."""
    from scipy import signal  # here: the simulated rig's process starts without it (a second of CPU)

    b, a = signal.butter(lp.order, 2.0 * np.pi * lp.cutoff_hz, btype="low", analog=True)
    A, B, C, D = signal.tf2ss(b, a)
    if np.any(np.abs(D) > 0):
        raise ValueError("a strictly proper low-pass was expected")
    return StateSpace(np.asarray(A), np.asarray(B).reshape(-1, 1), np.asarray(C))


def sensor_resonance_state_space(res: DisplacementResonance) -> StateSpace:
    """The displacement sensor's resonance x_m'' + 2 p w_r x_m' + w_r^2 x_m = w_r^2 x_b, state
    [x_m, x_m'], input x_b (m), output x_m (m): ``DisplacementResonance.response`` as state space."""
    w = 2.0 * np.pi * res.resonance_hz
    A = np.array([[0.0, 1.0], [-w * w, -2.0 * res.damping * w]])
    return StateSpace(A, np.array([[0.0], [w * w]]), np.array([[1.0, 0.0]]))


def spring_force_per_acceleration(t: Transducer, coupling: CouplingCompliance | None,
                                  f_hz: np.ndarray) -> np.ndarray:
    """Analytic k_f*Z2/(s^2 X_b) in N/(m/s^2) at f_hz (paper Eq. 8, or Eq. 9 when coupling is None)."""
    return spring_response(Laplace.at(f_hz, coupling is not None), t.k_f, t.b_f, t.m_e, t.m_l,
                           None if coupling is None else (coupling.k_c, coupling.b_c))


@dataclass(frozen=True)
class Laplace:
    """s = j 2 pi f (rad/s) at frequencies f (any shape) and its powers s^2, s^3, s^4 (s^3 and s^4 only
    for the coupled model, else None): what ``spring_response`` needs of the frequencies, made once for
    a model evaluated at the same frequencies many times."""

    s: np.ndarray
    s2: np.ndarray
    s3: np.ndarray | None
    s4: np.ndarray | None

    @classmethod
    def at(cls, f_hz: np.ndarray, coupled: bool) -> Laplace:
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        return cls(s, s**2, s**3 if coupled else None, s**4 if coupled else None)


def spring_response(lp: Laplace, k_f: float, b_f: float, m_e: float, m_l: float,
                    coupling: tuple[float, float] | None) -> np.ndarray:
    """``spring_force_per_acceleration`` (N/(m/s^2), the shape of the frequencies) from the stiffness
    k_f (N/m), damping b_f (N*s/m), end and load masses m_e, m_l (kg) and the coupling's (k_c N/m,
    b_c N*s/m) or None (stiff), at the frequencies of ``lp`` (its s^3 and s^4 are needed with a coupling)."""
    s = lp.s
    if coupling is None:
        M = m_e + m_l
        d1, d2 = b_f / M, k_f / M
        return -k_f / (lp.s2 + d1 * s + d2)
    if lp.s3 is None or lp.s4 is None:
        raise ValueError("the coupled model needs s^3 and s^4 (Laplace.at(f_hz, coupled=True))")
    me, ml, kf, bf, (kc, bc) = m_e, m_l, k_f, b_f, coupling
    u1 = ml * me / (ml + me)
    d1 = bc / u1 + bf / me
    d2 = kc / u1 + kf / me + bf * bc / (me * ml)
    d3 = (kf * bc + kc * bf) / (me * ml)
    d4 = kf * kc / (me * ml)
    n1, n2 = bc / u1, kc / u1
    return -kf * (lp.s2 + n1 * s + n2) / (lp.s4 + d1 * lp.s3 + d2 * lp.s2 + d3 * s + d4)


def force_signal_per_displacement(physics: RigPhysics, f_hz: np.ndarray) -> np.ndarray:
    """Analytic small-signal response of the recorded force voltage to the frame displacement,
    in V/m, with every *linear* effect that is switched on (coupling, low-pass, channel delay,
    the displacement sensor's resonance: force voltage per *measured* displacement).

    Nonlinear or additive effects (harmonics, nonlinearity, mains, drift) have no single-frequency
    transfer function and are not included.  The result is what a sine fit of the force-channel
    voltage divided by the displacement (in m) gives in steady state.
    """
    f = np.asarray(f_hz, dtype=float)
    s = 2j * np.pi * f
    e = physics.effects
    h = spring_force_per_acceleration(physics.transducer, e.coupling_compliance, f) * s**2
    h = h * physics.transducer.sensitivity_V_per_N * physics.conditioner.gain
    if e.conditioner_lowpass is not None:
        from scipy import signal

        b, a = signal.butter(e.conditioner_lowpass.order, 2 * np.pi * e.conditioner_lowpass.cutoff_hz,
                             btype="low", analog=True)
        h = h * np.polyval(b, s) / np.polyval(a, s)
    if e.channel_delay is not None:
        h = h * np.exp(2j * np.pi * f * e.channel_delay.delay_s)
    if e.displacement_resonance is not None:
        h = h / e.displacement_resonance.response(f)
    return h
