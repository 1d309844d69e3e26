"""The simulated rig's noise (``kernels.standard_normal``: counter-based standard normal draws): normal
by the distribution's own numbers (scipy's), white, the channels and seeds independent, and each
draw a function of its sample index alone, so a run's noise does not depend on its blocks."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from drivers.rig import kernels
from drivers.rig import params as rp
from drivers.rig.presets import paper_5kN_physics
from drivers.rig.synth import RigSynth

N = 1_000_000


def _draws(key: int, start: int, n: int) -> np.ndarray:
    out = np.empty(n)
    kernels.fill_standard_normal(np.uint64(key), start, out)
    return out


@pytest.fixture(scope="module")
def z() -> np.ndarray:
    return _draws(0x243F6A8885A308D3, 0, N)


def test_the_draws_are_standard_normal(z: np.ndarray) -> None:
    assert abs(z.mean()) < 5 / np.sqrt(N)
    assert abs(z.var() - 1.0) < 5 * np.sqrt(2 / N)
    # 100 bins of equal probability under N(0, 1): chi-square with 99 degrees of freedom
    counts = np.bincount(np.searchsorted(stats.norm.ppf(np.linspace(0, 1, 101)[1:-1]), z), minlength=100)
    assert stats.chisquare(counts).pvalue > 1e-4
    assert stats.kstest(z, "norm").pvalue > 1e-4


@pytest.mark.parametrize("beyond", [1.0, 3.0, kernels.ZIGGURAT_R, 4.5])
def test_the_tails_hold_their_share(z: np.ndarray, beyond: float) -> None:
    """Beyond the ziggurat's base strip (its tail algorithm) and inside it (its wedges)."""
    p = 2 * stats.norm.sf(beyond)
    got = np.count_nonzero(np.abs(z) > beyond)
    assert abs(got - N * p) < 5 * np.sqrt(N * p * (1 - p)) + 1


def test_the_draws_are_white_and_the_streams_independent(z: np.ndarray) -> None:
    f = np.fft.rfft(z - z.mean(), 2 * N)
    acf = np.fft.irfft(f * np.conj(f))[1:65] / N  # lags 1..64
    assert np.max(np.abs(acf)) < 5 / np.sqrt(N)
    other = _draws(0x243F6A8885A308D4, 0, N)  # the next key: a stream offset by one draw would show here
    for lag in (-1, 0, 1):
        r = np.corrcoef(np.roll(z, lag), other)[0, 1]
        assert abs(r) < 5 / np.sqrt(N)


def test_a_draw_is_a_function_of_its_index(z: np.ndarray) -> None:
    for start, n in [(0, 1), (1, 7), (777, 1000), (N - 3, 3)]:
        np.testing.assert_array_equal(_draws(0x243F6A8885A308D3, start, n), z[start:start + n])


def test_the_synthesised_noise_does_not_depend_on_the_blocks() -> None:
    """Every effect and both noises on: a run cut into other blocks gives the same noise draws (and the
    signal within rounding); another seed other noise, the same seed the same samples."""
    eff = rp.Effects(coupling_compliance=rp.CouplingCompliance(5e8, 400.0),
                     conditioner_lowpass=rp.ConditionerLowpass(4, 1000.0),
                     displacement_resonance=rp.DisplacementResonance(5000.0, 0.05))
    ph = paper_5kN_physics(eff)
    one = RigSynth(ph, seed=3, crank_radius_m=0.002)
    a = [one.advance(7000, 20.0), one.advance(9000, 20.0)]
    two = RigSynth(ph, seed=3, crank_radius_m=0.002)
    b, done = [], 0
    for n in (1, 333, 4000, 2666):  # the ramp in uneven pieces, the same linear profile
        done += n
        b.append(two.advance(n, 20.0 * done / 7000))
    b += [two.advance(4501, 20.0), two.advance(4499, 20.0)]
    for name in ("force_V", "displacement_V"):
        x, y = (np.concatenate([getattr(blk, name) for blk in blocks]) for blocks in (a, b))
        assert np.max(np.abs(x - y)) < 1e-9 * np.max(np.abs(x))  # a different draw would differ by ~1e-4 V
    quiet = RigSynth(paper_5kN_physics(eff, noise=False), seed=3, crank_radius_m=0.002)
    clean = np.concatenate([quiet.advance(7000, 20.0).force_V, quiet.advance(9000, 20.0).force_V])
    noise = np.concatenate([blk.force_V for blk in a]) - clean
    assert np.std(noise) == pytest.approx(ph.conditioner.noise_V, rel=0.03)
    again = RigSynth(ph, seed=3, crank_radius_m=0.002).advance(7000, 20.0)
    other = RigSynth(ph, seed=4, crank_radius_m=0.002).advance(7000, 20.0)
    np.testing.assert_array_equal(again.force_counts, a[0].force_counts)
    assert abs(np.corrcoef(other.force_V - clean[:7000], noise[:7000])[0, 1]) < 0.06
