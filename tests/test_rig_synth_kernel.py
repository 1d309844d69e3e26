"""The one-pass synthesis (``kernels.synth_block`` behind ``RigSynth.advance``) against the staged
synthesis (``RigSynth.advance_stages``: numpy stage by stage, its harmonic sums and filter bank
checked against their numpy/scipy definitions in test_rig_kernels): the same samples to the bit, for
every effect, steady and ramping crank, blocks of any length, the two interchangeable block by block;
one compiled signature serves every configuration (nothing compiles after the first block)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from drivers.rig import crank
from drivers.rig import params as rp
from drivers.rig.presets import paper_5kN_physics, paper_12k5N_physics
from drivers.rig.synth import RigSynth, SynthBlock

EVERY_EFFECT = rp.Effects(
    coupling_compliance=rp.CouplingCompliance(5e8, 400.0),
    conditioner_lowpass=rp.ConditionerLowpass(4, 1000.0),
    channel_delay=rp.ChannelDelay(2.5e-5),
    crank_harmonics=rp.CrankHarmonics(0.25),
    transducer_nonlinearity=rp.TransducerNonlinearity(0.01, 0.002),
    mains_interference=rp.MainsInterference((0.005, 0.001, 0.002), frequency_hz=50.0, phases_rad=(0.3,)),
    zero_drift=rp.ZeroDrift(1e-4, 2e-6),
    displacement_resonance=rp.DisplacementResonance(5000.0, 0.05),
    clock_skew=rp.ClockSkew(2e-4),
)
CASES = {
    "every-effect": paper_5kN_physics(EVERY_EFFECT),
    "no-effect": paper_5kN_physics(rp.Effects()),
    "no-effect-no-noise": paper_12k5N_physics(rp.Effects(), noise=False),
    # a sine crank (one harmonic), a low-pass of odd and of the highest order, the rate path without
    # the nonlinearity, a constant lag
    "sine-crank": paper_12k5N_physics(rp.Effects(conditioner_lowpass=rp.ConditionerLowpass(3, 800.0),
                                                 channel_delay=rp.ChannelDelay(-4e-5),
                                                 displacement_resonance=rp.DisplacementResonance(3000.0))),
    "order-8": paper_5kN_physics(rp.Effects(conditioner_lowpass=rp.ConditionerLowpass(8, 2000.0),
                                            crank_harmonics=rp.CrankHarmonics(0.05))),
    # lags beyond the Taylor series' 0.1 rad: a constant lag and the series about it in steady blocks,
    # the per-sample cos/sin given to the kernel in ramps
    "long-lag": paper_5kN_physics(rp.Effects(channel_delay=rp.ChannelDelay(1e-3), clock_skew=rp.ClockSkew(1e-3),
                                             mains_interference=rp.MainsInterference((0.01,), 60.0))),
    "far-lag-every-effect": paper_5kN_physics(replace(EVERY_EFFECT, channel_delay=rp.ChannelDelay(-7e-3))),
}
# (samples, crank frequency at the block's end in Hz): a ramp, steady blocks of odd lengths and of
# one sample, a ramp down to standstill, standstill
PLAN = [(3000, 20.0), (777, 20.0), (20_000, 20.0), (5000, 35.0), (256, 35.0), (1, 30.0), (513, 30.0),
        (4096, 0.0), (300, 0.0)]
FIELDS = ("displacement_counts", "force_counts", "displacement_V", "force_V", "displacement_m",
          "crank_frequency_hz", "start_sample", "clipped")


def _same(a: SynthBlock, b: SynthBlock) -> None:
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.mark.parametrize("case", list(CASES))
def test_one_pass_synthesis_is_the_staged_synthesis_to_the_bit(case: str) -> None:
    ph = CASES[case]
    fast = RigSynth(ph, seed=5, crank_radius_m=0.002)
    staged = RigSynth(ph, seed=5, crank_radius_m=0.002)
    for n, f in PLAN:
        a, b = fast.advance(n, f), staged.advance_stages(n, f)
        _same(a, b)
        assert a.force_V.size == n and (n == 1 or np.ptp(a.force_V) > 0)  # a signal, not empty arrays
    assert (fast.crank_angle_rad, fast.sample_index) == (staged.crank_angle_rad, staged.sample_index)


def test_every_way_of_lagging_the_displacement_is_exercised(monkeypatch: pytest.MonkeyPatch) -> None:
    """The cases above reach each of ``RigSynth._shift``'s modes (so the bit-for-bit test covers them)."""
    seen: set[int] = set()
    real = RigSynth._shift

    def spy(self: RigSynth, *a: float) -> tuple:
        got = real(self, *a)
        seen.add(got[0])
        return got

    monkeypatch.setattr(RigSynth, "_shift", spy)
    for case in CASES.values():
        s = RigSynth(case, seed=0, crank_radius_m=0.002)
        for n, f in PLAN:
            s.advance(n, f)
    assert seen == {0, 1, 2, 3, 4}


def test_the_two_paths_carry_the_same_state_block_by_block() -> None:
    ph = CASES["every-effect"]
    mixed = RigSynth(ph, seed=1, crank_radius_m=0.003)
    staged = RigSynth(ph, seed=1, crank_radius_m=0.003)
    for i, (n, f) in enumerate(PLAN):
        step = mixed.advance if i % 2 else mixed.advance_stages
        _same(step(n, f), staged.advance_stages(n, f))


def test_the_signal_is_the_crank_and_the_chain_not_an_artefact_of_the_kernel() -> None:
    """The one-pass output against what the rig must do, independently of either path: at standstill
    the gravity preload (-(m_e + m_l) g through the chain), in steady state the displacement the crank
    radius gives (through the sensor's gain)."""
    ph = replace(CASES["no-effect-no-noise"], adc=rp.Adc(bits=16, displacement_range_V=10.0, force_range_V=10.0))
    s = RigSynth(ph, seed=0, crank_radius_m=0.004)
    rest = s.advance(2000, 0.0)
    t = ph.transducer
    np.testing.assert_allclose(rest.force_V, -t.total_mass_kg * ph.gravity_m_per_s2 * t.sensitivity_V_per_N
                               * ph.conditioner.gain, rtol=1e-12)
    s.advance(20_000, 10.0)
    b = s.advance(20_000, 10.0)
    np.testing.assert_allclose(np.ptp(b.displacement_V) / 2, 0.004 * ph.displacement_sensor.gain_V_per_m, rtol=1e-6)


def test_one_compiled_signature_serves_every_configuration() -> None:
    """The emulator compiles the kernel at its first configuration (``RigSource._compile_once``); any
    other effect set, block length or crank profile must not compile it again while it answers."""
    from drivers.rig import kernels

    for ph in CASES.values():
        s = RigSynth(ph, seed=0, crank_radius_m=0.002)
        for n, f in PLAN[:6]:
            s.advance(n, f)
    assert len(kernels.synth_block.signatures) == 1


def test_cos_sin_is_within_rounding_of_the_complex_product() -> None:
    """The rotation tables' product written out in real arithmetic (the same on every CPU, and what the
    kernel computes) is within float rounding of numpy's complex product (which fuses a multiply-add
    on some CPUs), and both of cos and sin of the angle."""
    phi0, dphi, n = 1.234, 2 * np.pi * 37.5 / 20_000, 50_000
    c, s = crank.cos_sin(phi0, dphi, 0.0, n)
    (br, bi), (tr, ti) = crank.rotations(phi0, dphi, n)
    e = np.multiply.outer(br + 1j * bi, tr + 1j * ti).ravel()[:n]
    assert np.max(np.abs(c - e.real)) <= 2.3e-16 and np.max(np.abs(s - e.imag)) <= 2.3e-16
    phi = phi0 + dphi * np.arange(n)  # up to 600 rad: the tables' angles rounded to ~1e-13 rad
    assert np.max(np.abs(c - np.cos(phi))) < 1e-12 and np.max(np.abs(s - np.sin(phi))) < 1e-12
