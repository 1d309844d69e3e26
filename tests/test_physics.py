"""The simulated rig against closed forms: Eq. 8/9 frequency responses, the static limit
F = -(m_e+m_l) a, the gravity preload, and each effect's own signature."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import signal

from drivers.rig import params as rp
from drivers.rig.model import force_signal_per_displacement, spring_force_per_acceleration
from drivers.rig.presets import paper_5kN_physics, paper_12k5N_physics
from drivers.rig.synth import RigSynth

FS = 20_000.0
COUPLING = rp.CouplingCompliance(k_c=5e8, b_c=400.0)


def sine_fit(y: np.ndarray, f: float, fs: float = FS) -> complex:
    """Complex amplitude A of y ~ Im(A exp(i w t)) + c (least squares, integer periods)."""
    t = np.arange(y.size) / fs
    X = np.column_stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t), np.ones_like(t)])
    c, *_ = np.linalg.lstsq(X, y, rcond=None)
    return complex(c[0], c[1])


def steady_block(physics: rp.RigPhysics, f: float, radius: float = 1e-4, periods: int = 10,
                 settle_s: float = 1.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(displacement_V, force_V, displacement_m) of whole periods after ramp-up and settling."""
    s = RigSynth(physics, seed=0, crank_radius_m=radius)
    s.advance(int(FS * 0.5), f)  # ramp
    s.advance(int(FS * settle_s), f)
    n = round(FS / f * periods)
    b = s.advance(n, f)
    return b.displacement_V, b.force_V, b.displacement_m


def measured_frf(physics: rp.RigPhysics, f: float, **kw: float) -> complex:
    dv, fv, _ = steady_block(physics, f, **kw)
    return sine_fit(fv, f) / sine_fit(dv, f) * physics.displacement_sensor.gain_V_per_m


@pytest.mark.parametrize("coupled", [False, True], ids=["eq9-stiff", "eq8-coupled"])
@pytest.mark.parametrize("make", [paper_5kN_physics, paper_12k5N_physics], ids=["5kN", "12k5N"])
def test_frequency_response_matches_eq8_eq9(make, coupled: bool) -> None:
    eff = rp.Effects(coupling_compliance=COUPLING if coupled else None)
    ph = make(eff, noise=False)
    t = ph.transducer
    gain = t.sensitivity_V_per_N * ph.conditioner.gain
    for f in (1.0, 4.0, 17.0, 55.0, 100.0, 400.0, 1000.0):
        # the README's claim: ~1e-9 at 100 Hz, ~1e-5 at 1 kHz (the discretisation error grows as f^4)
        tol = max(1e-11, 2e-9 * (f / 100.0) ** 4)
        periods = 4 if f < 10 else 40
        h = measured_frf(ph, f, periods=periods)
        # Eq. 8/9 written out here independently of drivers.rig.model
        s = 2j * np.pi * f
        if coupled:
            me, ml, kf, bf, kc, bc = t.m_e, t.m_l, t.k_f, t.b_f, COUPLING.k_c, COUPLING.b_c
            u1 = ml * me / (ml + me)
            num = s**2 + bc / u1 * s + kc / u1
            den = (s**4 + (bc / u1 + bf / me) * s**3 + (kc / u1 + kf / me + bf * bc / (me * ml)) * s**2
                   + (kf * bc + kc * bf) / (me * ml) * s + kf * kc / (me * ml))
            z2 = -num / den
        else:
            M = t.m_e + t.m_l
            z2 = -1.0 / (s**2 + t.b_f / M * s + t.k_f / M)
        expected = gain * t.k_f * z2 * s**2  # force voltage per metre of frame displacement
        assert abs(h / expected - 1) < tol, (f, abs(h / expected - 1))


def test_model_module_agrees_with_the_independent_formula() -> None:
    ph = paper_5kN_physics(rp.Effects(coupling_compliance=COUPLING), noise=False)
    f = np.array([3.0, 30.0, 300.0])
    h = force_signal_per_displacement(ph, f)
    ratio = h / (spring_force_per_acceleration(ph.transducer, COUPLING, f) * (2j * np.pi * f) ** 2)
    assert np.allclose(ratio, ph.transducer.sensitivity_V_per_N * ph.conditioner.gain, rtol=1e-14)


@pytest.mark.parametrize("coupled", [False, True])
def test_static_limit_force_is_minus_total_mass_times_acceleration(coupled: bool) -> None:
    """At 1 Hz (f/fn ~ 6e-3) the force signal is -S (m_e+m_l)(a+g), the dynamic deviation being
    |H/H(0) - 1| ~ 2 zeta f/fn + (f/fn)^2 of the amplitude (zeta the damping ratio)."""
    ph = paper_5kN_physics(rp.Effects(coupling_compliance=COUPLING if coupled else None), noise=False)
    t = ph.transducer
    S = t.sensitivity_V_per_N * ph.conditioner.gain
    f, r = 1.0, 0.02
    _dv, fv, x = steady_block(ph, f, radius=r, periods=2)
    a = -(2 * np.pi * f) ** 2 * x
    predicted = -S * (t.m_e + t.m_l) * (a + ph.gravity_m_per_s2)
    fn = np.sqrt(t.k_f / (t.m_e + t.m_l)) / (2 * np.pi)
    amp = S * (t.m_e + t.m_l) * r * (2 * np.pi * f) ** 2
    zeta = t.b_f / (2 * np.sqrt(t.k_f * (t.m_e + t.m_l)))
    dyn = 2 * zeta * f / fn + (f / fn) ** 2
    assert np.max(np.abs(fv - predicted)) < 1.2 * dyn * amp
    assert np.max(np.abs(fv - predicted)) > 0.5 * dyn * amp  # the dynamics are really there


@pytest.mark.parametrize("coupled", [False, True])
def test_gravity_preload_at_standstill(coupled: bool) -> None:
    ph = paper_12k5N_physics(rp.Effects(coupling_compliance=COUPLING if coupled else None), noise=False)
    b = RigSynth(ph, seed=0, crank_radius_m=0.01).advance(5000, 0.0)
    t = ph.transducer
    expected = -t.sensitivity_V_per_N * ph.conditioner.gain * (t.m_e + t.m_l) * ph.gravity_m_per_s2
    assert np.allclose(b.force_V, expected, rtol=1e-12, atol=0)
    assert np.allclose(b.displacement_V, 0.0, atol=1e-15)  # crank at phi0 = 0


def test_block_size_does_not_change_the_signal() -> None:
    eff = rp.Effects(coupling_compliance=COUPLING, conditioner_lowpass=rp.ConditionerLowpass(2, 800.0),
                     crank_harmonics=rp.CrankHarmonics(0.2))
    ph = paper_5kN_physics(eff, noise=False)
    one = RigSynth(ph, seed=3, crank_radius_m=0.002)
    a = np.concatenate([one.advance(7000, 20.0).force_V, one.advance(9000, 20.0).force_V])
    two = RigSynth(ph, seed=3, crank_radius_m=0.002)
    parts = []
    f_prev, done = 0.0, 0
    for n in (1, 333, 4000, 2666):  # ramp cut into uneven pieces, same linear profile
        done += n
        f_end = 20.0 * done / 7000
        parts.append(two.advance(n, f_end).force_V)
        f_prev = f_end
    assert f_prev == pytest.approx(20.0)
    parts += [two.advance(4500, 20.0).force_V, two.advance(4500, 20.0).force_V]
    b = np.concatenate(parts)
    assert np.max(np.abs(a - b)) < 1e-10 * np.max(np.abs(a))


def test_ramp_follows_the_motor_profile() -> None:
    ph = paper_5kN_physics(noise=False)
    s = RigSynth(ph, seed=0, crank_radius_m=0.01)
    b = s.advance(20_000, 5.0)  # 1 s ramp 0 -> 5 Hz
    assert b.crank_frequency_hz[0] == 0.0
    assert np.allclose(np.diff(b.crank_frequency_hz), 5.0 / 20_000)
    # angle after the ramp: 2 pi * mean frequency * duration = 2 pi * 2.5 rev
    assert s.crank_angle_rad == pytest.approx(np.mod(2 * np.pi * 2.5, 2 * np.pi), abs=1e-9)
    # a run starts from rest: x = r sin(pi * rate * t^2) during a ramp from standstill
    t = np.arange(20_000) / FS
    assert np.allclose(b.displacement_m, 0.01 * np.sin(np.pi * 5.0 * t**2), rtol=0, atol=1e-12)


# ---- effect signatures ------------------------------------------------------------------------

def test_channel_delay_shifts_phase_by_2_pi_f_dt() -> None:
    base = paper_5kN_physics(noise=False)
    for dt in (2e-5, -3.7e-5):
        ph = replace(base, effects=rp.Effects(channel_delay=rp.ChannelDelay(dt)))
        for f in (4.0, 50.0):
            ratio = measured_frf(ph, f) / measured_frf(base, f)
            assert abs(ratio) == pytest.approx(1.0, abs=1e-7)
            assert np.angle(ratio) == pytest.approx(2 * np.pi * f * dt, abs=1e-8)


def test_a_large_drifting_lag_is_the_exact_shift() -> None:
    """A lag of about half a radian that the clock skew moves sample by sample (beyond the 0.1 rad the
    synthesis's Taylor series covers on its own): every displacement sample is the sine crank's
    r sin(phi_k - 2 pi f d_k) at the lag d_k = delay - skew t_k, to rounding."""
    ph = paper_5kN_physics(rp.Effects(channel_delay=rp.ChannelDelay(4e-3), clock_skew=rp.ClockSkew(1e-4)), noise=False)
    s = RigSynth(ph, seed=0, crank_radius_m=1e-3)
    f, r, gain = 20.0, 1e-3, ph.displacement_sensor.gain_V_per_m
    s.advance(10_000, f)
    s.advance(30_001, f)
    phi0, k0 = s.crank_angle_rad, s.sample_index
    b = s.advance(20_000, f)
    k = np.arange(b.displacement_V.size)
    lag = 4e-3 - 1e-4 * (k0 + k) / FS
    want = gain * r * np.sin(phi0 + 2 * np.pi * f * k / FS - 2 * np.pi * f * lag)
    assert np.max(np.abs(b.displacement_V - want)) < 1e-9 * gain * r


def test_conditioner_lowpass_is_a_butterworth() -> None:
    base = paper_5kN_physics(noise=False)
    lp = rp.ConditionerLowpass(order=4, cutoff_hz=150.0)
    ph = replace(base, effects=rp.Effects(conditioner_lowpass=lp))
    b, a = signal.butter(4, 2 * np.pi * 150.0, analog=True)
    for f in (10.0, 100.0, 150.0):
        ratio = measured_frf(ph, f, periods=20) / measured_frf(base, f, periods=20)
        _, h = signal.freqs(b, a, worN=[2 * np.pi * f])
        assert abs(ratio / h[0] - 1) < 1e-6
    # -3 dB at the cut-off
    assert abs(measured_frf(ph, 150.0, periods=20) / measured_frf(base, 150.0, periods=20)) == \
        pytest.approx(2**-0.5, rel=1e-6)


def test_displacement_sensor_resonance_is_a_second_order_low_pass_on_the_displacement() -> None:
    """The measured displacement is w_r^2/(w_r^2 - w^2 + 2j p w_r w) times the frame's (written out
    here), the force channel untouched; the analytic small-signal response says the same."""
    base = paper_5kN_physics(noise=False)
    for fr, p in ((600.0, 0.3), (600.0, 1.0)):
        res = rp.DisplacementResonance(resonance_hz=fr, damping=p)
        ph = replace(base, effects=rp.Effects(displacement_resonance=res))
        for f in (10.0, 40.0, 300.0):
            ratio = measured_frf(ph, f, periods=20) / measured_frf(base, f, periods=20)
            w, wr = 2 * np.pi * f, 2 * np.pi * fr
            expected = (wr * wr - w * w + 2j * p * wr * w) / (wr * wr)  # force per measured displacement
            assert abs(ratio / expected - 1) < 1e-6
            analytic = force_signal_per_displacement(ph, np.array([f])) / force_signal_per_displacement(
                base, np.array([f]))
            assert abs(analytic[0] / expected - 1) < 1e-12


def test_crank_harmonics_of_a_slider_crank() -> None:
    r, L, f = 0.01, 0.15, 5.0
    ph = paper_5kN_physics(rp.Effects(crank_harmonics=rp.CrankHarmonics(L)), noise=False)
    _dv, fv, x = steady_block(ph, f, radius=r, periods=4)
    lam = r / L
    # sqrt(L^2 - r^2 cos^2) = L - L (lam^2/4 + lam^4/16 + ...) cos(2 phi) + ...
    a2 = abs(sine_fit(x, 2 * f))
    assert a2 == pytest.approx(r * lam / 4 * (1 + lam**2 / 4), rel=2e-3)
    assert abs(sine_fit(x, f)) == pytest.approx(r, rel=1e-9)
    # the force channel responds to the second harmonic as the transfer function says
    h2 = sine_fit(fv, 2 * f) / sine_fit(x, 2 * f)
    h2_expected = force_signal_per_displacement(paper_5kN_physics(noise=False), np.array([2 * f]))[0]
    assert abs(h2 / h2_expected - 1) < 1e-5


def test_transducer_nonlinearity_is_a_static_map_of_the_force() -> None:
    base = paper_5kN_physics(noise=False)
    nl = rp.TransducerNonlinearity(quadratic=0.02, cubic=-0.01)
    ph = replace(base, effects=rp.Effects(transducer_nonlinearity=nl))
    f, r = 8.0, 0.01
    _, lin, _ = steady_block(base, f, radius=r, periods=4)
    _, out, _ = steady_block(ph, f, radius=r, periods=4)
    S, C = base.transducer.sensitivity_V_per_N * base.conditioner.gain, base.transducer.capacity_N
    F = lin / S
    expected = S * F * (1 + nl.quadratic * F / C + nl.cubic * (F / C) ** 2)
    assert np.max(np.abs(out - expected)) < 1e-12 * np.max(np.abs(out))
    # its signature: harmonics in the force channel only; 2nd harmonic = S q F1^2 / (2 C) + cubic part
    F0, F1 = np.mean(F), abs(sine_fit(F, f))
    a2 = abs(sine_fit(out, 2 * f))
    a2_expected = abs(S * (nl.quadratic * F1**2 / (2 * C) + nl.cubic * 3 * F0 * F1**2 / (2 * C**2)))
    assert a2 == pytest.approx(a2_expected, rel=1e-3)


def test_mains_interference_adds_exact_lines() -> None:
    base = paper_5kN_physics(noise=False)
    m = rp.MainsInterference(frequency_hz=50.0, amplitudes_V=(0.01, 0.0, 0.004), phases_rad=(0.3, 0.0, -1.0))
    ph = replace(base, effects=rp.Effects(mains_interference=m))
    s0, s1 = RigSynth(base, seed=0, crank_radius_m=0.01), RigSynth(ph, seed=0, crank_radius_m=0.01)
    s0.advance(10_000, 4.0), s1.advance(10_000, 4.0)
    d = s1.advance(20_000, 4.0).force_V - s0.advance(20_000, 4.0).force_V
    t = (10_000 + np.arange(20_000)) / FS
    expected = 0.01 * np.sin(2 * np.pi * 50 * t + 0.3) + 0.004 * np.sin(2 * np.pi * 150 * t - 1.0)
    assert np.max(np.abs(d - expected)) < 1e-12


def test_zero_drift_is_a_slow_offset_ramp() -> None:
    base = paper_5kN_physics(noise=False)
    z = rp.ZeroDrift(rate_V_per_s=2e-3, quadratic_V_per_s2=-1e-5)
    ph = replace(base, effects=rp.Effects(zero_drift=z))
    s0, s1 = RigSynth(base, seed=0, crank_radius_m=0.01), RigSynth(ph, seed=0, crank_radius_m=0.01)
    d = s1.advance(60_000, 6.0).force_V - s0.advance(60_000, 6.0).force_V
    t = np.arange(60_000) / FS
    assert np.max(np.abs(d - (2e-3 * t - 1e-5 * t**2))) < 1e-12


def test_coupling_compliance_lowers_the_resonance() -> None:
    ph0 = paper_12k5N_physics(noise=False)
    ph1 = replace(ph0, effects=rp.Effects(coupling_compliance=rp.CouplingCompliance(2e8, 100.0)))
    f = np.linspace(50, 400, 3501)
    k0 = f[np.argmax(np.abs(spring_force_per_acceleration(ph0.transducer, None, f)))]
    k1 = f[np.argmax(np.abs(spring_force_per_acceleration(ph1.transducer, ph1.effects.coupling_compliance, f)))]
    # series stiffness k_f k_c / (k_f + k_c) moves the first resonance down by about sqrt of that ratio
    t = ph0.transducer
    ratio = np.sqrt(2e8 / (2e8 + t.k_f))
    assert k1 / k0 == pytest.approx(ratio, rel=5e-3)


# ---- sensor chain --------------------------------------------------------------------------------

def test_adc_quantises_and_clips() -> None:
    ph = paper_5kN_physics(noise=False)
    ph = replace(ph, adc=rp.Adc(bits=12, displacement_range_V=1.0, force_range_V=10.0))
    b = RigSynth(ph, seed=0, crank_radius_m=0.01).advance(20_000, 4.0)  # 0.01 m * 500 V/m = 5 V > 1 V
    lsb_d = ph.adc.volts_per_count(1.0)
    assert b.displacement_counts.max() == 2**11 - 1 and b.displacement_counts.min() == -(2**11)
    assert b.clipped > 0
    inside = np.abs(b.displacement_V) < 0.9
    assert np.all(np.abs(b.displacement_counts[inside] * lsb_d - b.displacement_V[inside]) <= lsb_d / 2 + 1e-15)


def test_noise_levels_and_seeds() -> None:
    ph = paper_5kN_physics()
    a = RigSynth(ph, seed=11, crank_radius_m=0.01).advance(40_000, 0.0)
    b = RigSynth(ph, seed=11, crank_radius_m=0.01).advance(40_000, 0.0)
    c = RigSynth(ph, seed=12, crank_radius_m=0.01).advance(40_000, 0.0)
    assert np.array_equal(a.force_counts, b.force_counts)
    assert not np.array_equal(a.force_counts, c.force_counts)
    assert np.std(a.force_V) == pytest.approx(ph.conditioner.noise_V, rel=0.03)
    noise_V = ph.displacement_sensor.noise_m * ph.displacement_sensor.gain_V_per_m
    assert np.std(a.displacement_V) == pytest.approx(noise_V, rel=0.03)
