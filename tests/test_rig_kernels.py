"""The synthesis's compiled loops (``drivers.rig.kernels``) against their numpy/scipy definitions:
the harmonic sums against the explicit (2K, n) Chebyshev stack, the filter bank against
``scipy.signal.lfilter`` with its states carried from block to block."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from drivers.rig import crank
from drivers.rig import params as rp
from drivers.rig.discretize import FilterBank, hermite_discretize
from drivers.rig.model import lowpass_state_space, mechanical_state_space, sensor_resonance_state_space
from drivers.rig.presets import paper_5kN_physics


@pytest.mark.parametrize("K,n", [(1, 7), (3, 1000), (7, 1537)])
def test_harmonic_sum_is_the_weighted_chebyshev_stack(K: int, n: int) -> None:
    rng = np.random.default_rng(K)
    phi = rng.uniform(0, 2 * np.pi, n)
    cs = (np.cos(phi), np.sin(phi))
    W = rng.normal(size=(4, 2 * K))
    got = crank.harmonic_sum(cs, W)
    np.testing.assert_allclose(got, W @ crank.harmonic_stack(cs, K), rtol=0, atol=1e-13 * np.abs(W).sum())
    # and the stack is what it claims: cos(h phi), sin(h phi)
    h = np.arange(1, K + 1)[:, None]
    np.testing.assert_allclose(got, W @ np.vstack([np.cos(h * phi), np.sin(h * phi)]), rtol=0, atol=1e-11 * K**2)



def test_harmonic_sums_of_any_row_count_are_each_rows_own() -> None:
    """The compiled sums take 1, 2 and 4 rows in passes of their own and split other counts into those:
    each row's sum is the same, to the bit, as that row summed alone, for odd and even harmonic counts."""
    rng = np.random.default_rng(0)
    phi = rng.uniform(0, 2 * np.pi, 600)
    cs = (np.cos(phi), np.sin(phi))
    for K in (1, 2, 3, 4, 5):
        for rows in range(1, 8):
            W = rng.normal(size=(rows, 2 * K))
            got = crank.harmonic_sum(cs, W)
            for i in range(rows):
                alone = crank.harmonic_sum(cs, W[i:i + 1])[0]
                np.testing.assert_array_equal(got[i], alone, err_msg=f"{K=} {rows=} {i=}")
            np.testing.assert_allclose(got, W @ crank.harmonic_stack(cs, K), rtol=0, atol=1e-13 * np.abs(W).sum())

@pytest.mark.parametrize("rod", [None, 0.25, 0.01])
def test_the_displacement_at_one_angle_is_the_series(rod: float | None) -> None:
    """The starting displacement the synthesiser's sensor state takes (numpy, nothing compiled) is x_b(phi)."""
    coeffs = crank.displacement_coefficients(0.004, rp.CrankHarmonics(rod) if rod else None)
    for phi in (0.0, 1.0, 4.5):
        want = crank.displacement_at(coeffs, (np.array([np.cos(phi)]), np.array([np.sin(phi)])))[0]
        assert crank.displacement_at_angle(coeffs, phi) == pytest.approx(want, rel=0, abs=1e-17)
    # and it is the slider-crank's geometry, not only the series: x = r sin phi - (L - sqrt(L^2 - r^2 cos^2 phi))
    if rod:
        x = 0.004 * np.sin(1.0) - (rod - np.sqrt(rod**2 - (0.004 * np.cos(1.0)) ** 2))
        dc = np.mean(0.004 * np.sin(p := np.linspace(0, 2 * np.pi, 4096, endpoint=False))
                     - (rod - np.sqrt(rod**2 - (0.004 * np.cos(p)) ** 2)))
        # the series drops harmonics below 1e-12 r
        assert crank.displacement_at_angle(coeffs, 1.0) == pytest.approx(x - dc, rel=0, abs=2e-14)


def _lfilter_bank(filters, u0: float, u: np.ndarray, du: np.ndarray, cuts: list[int]) -> np.ndarray:
    """The filter bank written with lfilter: two filters per output, their states carried across cuts."""
    zu = filters.zi_unit_u * u0
    zdu = np.zeros_like(zu)
    out = []
    for a, b in zip([0, *cuts], [*cuts, u.size], strict=True):
        rows = []
        for p in range(filters.n_outputs):
            y1, zu[p] = signal.lfilter(filters.num_u[p], filters.den, u[a:b], zi=zu[p])
            y2, zdu[p] = signal.lfilter(filters.num_du[p], filters.den, du[a:b], zi=zdu[p])
            rows.append(y1 + y2)
        out.append(np.array(rows))
    return np.hstack(out)


@pytest.mark.parametrize("which", ["coupled", "lowpass", "sensor"])
def test_filter_bank_is_lfilter_with_carried_states(which: str) -> None:
    T = 1 / 20_000
    t = paper_5kN_physics(rp.Effects()).transducer
    ss = {"coupled": mechanical_state_space(t, rp.CouplingCompliance(5e8, 400.0)),
          "lowpass": lowpass_state_space(rp.ConditionerLowpass(4, 1000.0)),
          "sensor": sensor_resonance_state_space(rp.DisplacementResonance(5000.0, 0.05))}[which]
    filters = hermite_discretize(ss, T)
    k = np.arange(6000) * T
    w = 2 * np.pi * np.linspace(3.0, 40.0, k.size)
    u, du = 9.8 + 30 * np.sin(w * k), 30 * w * np.cos(w * k)
    cuts = [1, 2500, 2501, 4000]
    bank = FilterBank(filters, u0=9.8)
    got = np.hstack([np.array(bank.run(u[a:b], du[a:b])) for a, b in zip([0, *cuts], [*cuts, u.size], strict=True)])
    ref = _lfilter_bank(filters, 9.8, u, du, cuts)
    scale = np.abs(ref).max(axis=1, keepdims=True)
    assert np.max(np.abs(got - ref) / scale) < 1e-12
    # one block or five: the same samples to the bit (the state carries over exactly)
    whole = np.array(FilterBank(filters, u0=9.8).run(u, du))
    np.testing.assert_array_equal(got, whole)


@pytest.mark.parametrize("which", ["coupled", "lowpass", "sensor"])
def test_transfer_functions_and_steady_states_are_scipy_signals(which: str) -> None:
    """The simulated rig's process builds its filters without importing scipy.signal: the same
    numerators, denominator and steady states as ``ss2tf`` and ``lfilter_zi`` compute."""
    from drivers.rig.discretize import lfilter_zi, ss2tf

    t = paper_5kN_physics(rp.Effects()).transducer
    ss = {"coupled": mechanical_state_space(t, rp.CouplingCompliance(5e8, 400.0)),
          "lowpass": lowpass_state_space(rp.ConditionerLowpass(4, 1000.0)),
          "sensor": sensor_resonance_state_space(rp.DisplacementResonance(5000.0, 0.05))}[which]
    rng = np.random.default_rng(3)
    p, n = ss.C.shape
    B2, D = np.hstack([ss.B, rng.normal(size=(n, 1))]), rng.normal(size=(p, 2))
    for i in (0, 1):
        num, den = ss2tf(ss.A, B2, ss.C, D, i)
        ref_num, ref_den = signal.ss2tf(ss.A, B2, ss.C, D, input=i)
        np.testing.assert_allclose(den, ref_den, rtol=1e-13)
        np.testing.assert_allclose(num, ref_num, rtol=1e-12, atol=1e-12 * np.abs(ref_num).max())
    filters = hermite_discretize(ss, 1 / 20_000)
    for k in range(p):
        ref_zi = signal.lfilter_zi(filters.num_u[k], filters.den)
        np.testing.assert_allclose(filters.zi_unit_u[k], ref_zi, rtol=1e-9, atol=1e-12 * np.abs(ref_zi).max())
    # a shorter numerator, a denominator not normalised
    np.testing.assert_allclose(lfilter_zi(np.array([0.5, 0.2]), np.array([2.0, -1.0, 0.3])),
                               signal.lfilter_zi([0.5, 0.2], [2.0, -1.0, 0.3]), rtol=1e-14)
