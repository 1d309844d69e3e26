"""Expert estimators against known truth and the Cramér-Rao bound (crb.py)."""

import numpy as np
import pytest

from station.ident.crb import crb_stepped_sine
from station.ident.identifiability import correlations
from station.ident.models import SdofModel
from station.ident.response.frf import fit_frf, linear_start_sdof
from station.ident.response.sinefit import design, fit3, fit4, unit_circle
from station.ident.synthetic import stepped_sine

M5 = SdofModel(0.12, 26.167)
TH5 = np.array([2e-3, 2.91e7, 17136.0])
F = np.array([4.0, 12.0, 30.0, 60.0, 100.0])
R = np.array([0.01, 0.004, 0.001, 4e-4, 1.5e-4])
FS, DUR, SX, SU = 5000.0, 0.25, 2e-7, 5e-4


def _estimate(seed: int) -> tuple[np.ndarray, np.ndarray, list, np.ndarray]:
    from station.ident.synthetic import response_of
    steps = stepped_sine(M5, TH5, F, R, fs_hz=FS, duration_s=DUR, sigma_x_m=SX, sigma_u_V=SU, seed=seed)
    frf = response_of(steps)
    fit = fit_frf(frf, M5, linear_start_sdof(frf, M5))
    return fit.theta, np.sqrt(np.diag(fit.cov)), steps, correlations(fit.cov)


def test_fd_recovers_k_f_within_0p1_percent_and_b_f_within_2_percent() -> None:
    theta, std, _, _ = _estimate(seed=123)
    assert abs(theta[1] / TH5[1] - 1) < 1e-3
    assert abs(theta[2] / TH5[2] - 1) < 0.02
    assert abs(theta[0] / TH5[0] - 1) < 1e-4
    assert np.all(std > 0)


@pytest.mark.slow
def test_fd_standard_deviations_reach_the_cramer_rao_bound_over_200_draws() -> None:
    draws = [_estimate(seed) for seed in range(200)]
    est = np.array([d[0] for d in draws])
    reported = np.array([d[1] for d in draws])
    steps = draws[0][2]
    crb = crb_stepped_sine(M5, TH5, F, [s.t.size for s in steps], R, SX, SU)
    ratio = est.std(axis=0, ddof=1) / crb.std
    assert np.all(ratio < 1.2), ratio
    assert np.all(ratio > 0.8), ratio  # 200 draws: the std itself is known to ~5 %
    # unbiased at the resolution of 200 draws
    assert np.all(np.abs(est.mean(axis=0) - TH5) < 4 * crb.std / np.sqrt(200))
    # the covariance each fit reports (Jacobian) agrees with the Monte Carlo scatter
    np.testing.assert_allclose(reported.mean(axis=0) / est.std(axis=0, ddof=1), 1.0, atol=0.2)
    # ... and so do its correlations (200 draws: a correlation is known to about +-0.07)
    mc_corr = np.corrcoef(est.T)
    fit_corr = np.array([d[3] for d in draws]).mean(axis=0)
    np.testing.assert_allclose(fit_corr, mc_corr, atol=0.2)


def test_sine_fit_covariance_matches_monte_carlo() -> None:
    rng = np.random.default_rng(7)
    t = np.arange(2000) / 2000.0
    X = 0.3 - 0.4j
    vals, covs = [], []
    for _ in range(300):
        y = (X * np.exp(2j * np.pi * 7 * (t - t.mean()))).real + 0.1 + rng.normal(0, 0.05, t.size)
        f3 = fit3(t, y, 7.0)
        vals.append(f3.phasor)
        covs.append(f3.phasor_cov)
    vals = np.array(vals)
    assert abs(vals.mean() - X) < 4 * 0.05 * np.sqrt(2 / t.size / 300)
    emp = np.cov(np.vstack([vals.real, vals.imag]))
    np.testing.assert_allclose(np.mean(covs, axis=0), emp, atol=0.25 * emp[0, 0])
    assert emp[0, 0] == pytest.approx(2 * 0.05**2 / t.size, rel=0.25)


def test_four_parameter_fit_finds_the_frequency() -> None:
    rng = np.random.default_rng(8)
    t = np.arange(4000) / 4000.0
    y = 2.0 * np.sin(2 * np.pi * 12.013 * t + 0.4) + rng.normal(0, 0.01, t.size)
    f4 = fit4(t, y, 12.0)
    assert f4.frequency_hz == pytest.approx(12.013, abs=5 * f4.frequency_std_hz)
    assert 0 < f4.frequency_std_hz < 1e-3
    assert abs(f4.phasor) == pytest.approx(2.0, rel=1e-3)


def test_the_sine_fits_design_holds_the_complex_exponentials_numbers() -> None:
    """The design of the sine fits (and the model gap's harmonics) is built from cosines and sines
    written as complex pairs; its columns must be exactly the numbers of exp(j w t) and of its powers
    taken as successive complex products, bit for bit (what the fits' results rest on)."""
    t = (np.arange(4001) - 2000.0) / 20_000.0
    for w in (2 * np.pi * 4.0, 2 * np.pi * 97.31, 2 * np.pi * 1234.5):
        e = np.exp(1j * w * t)
        z = unit_circle(w * t)
        assert np.array_equal(z.real, e.real) and np.array_equal(z.imag, e.imag)
        for n_h in (1, 3, 5):
            J = design(t, w, n_h)
            want = [e.real, e.imag, np.ones_like(t)]
            eh = e
            for _ in range(2, n_h + 1):
                eh = eh * e
                want += [eh.real, eh.imag]
            assert J.shape == (t.size, 1 + 2 * n_h)
            for col, ref in enumerate(want):
                assert np.array_equal(J[:, col], ref), (w, n_h, col)


@pytest.mark.slow
def test_oe_reported_uncertainty_matches_monte_carlo() -> None:
    from station.ident.oe import fit_oe
    from station.ident.response.checked import StepSignal
    from station.ident.response.frf import step_response
    est, rep = [], []
    for seed in range(60):
        steps = stepped_sine(M5, TH5, F, R, fs_hz=FS, duration_s=DUR, sigma_x_m=SX, sigma_u_V=SU, seed=seed)
        sigs = []
        for s in steps:
            it = step_response(s.t, s.x, s.u, s.f_hz)
            sigs.append(StepSignal(s.t, s.u, it[2], np.array((it[2].phasor, *it[2].harmonics))))
        fit = fit_oe(sigs, M5, TH5 * 1.01)
        est.append(fit.theta)
        rep.append(np.sqrt(np.diag(fit.cov)))
    est = np.array(est)
    ratio = np.mean(rep, axis=0) / est.std(axis=0, ddof=1)
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio
    assert abs(est[:, 1].mean() / TH5[1] - 1) < 1e-3


def test_a_step_is_fitted_once_and_anything_it_depends_on_fits_it_again(monkeypatch: pytest.MonkeyPatch) -> None:
    """``step_response`` keeps a step's fits by content: the same samples and settings give the kept
    item (equal to the one computed, not fitted again, its arrays the caller's own); a changed sample,
    dtype, frequency start, harmonic count or fixed frequency is fitted anew."""
    import station.ident.response.frf as frf

    s = stepped_sine(M5, TH5, F[:1], R[:1], fs_hz=FS, duration_s=DUR, sigma_x_m=SX, sigma_u_V=SU, seed=5)[0]
    frf.step_cache_clear()
    fitted: list[float] = []
    computed = frf._step_response
    monkeypatch.setattr(frf, "_step_response", lambda *a: fitted.append(a[3]) or computed(*a))
    first = frf.step_response(s.t, s.x, s.u, s.f_hz)
    first[1][0, 0] = np.nan  # the caller's copy: the kept item is not changed through it
    first[2].phasor_cov[0, 0] = np.nan
    again = frf.step_response(s.t.copy(), s.x.copy(), s.u.copy(), s.f_hz)
    assert len(fitted) == 1
    fresh = computed(s.t, s.x, s.u, s.f_hz, 3, True)
    assert again[0] == fresh[0] and np.array_equal(again[1], fresh[1])
    for kept, fit in zip(again[2:], fresh[2:], strict=True):  # the sine fits, field by field
        assert np.array_equal(kept.phasor_cov, fit.phasor_cov)
        assert (kept.frequency_hz, kept.frequency_std_hz, kept.phasor, kept.offset, kept.residual_rms,
                kept.harmonics) == (fit.frequency_hz, fit.frequency_std_hz, fit.phasor, fit.offset,
                                    fit.residual_rms, fit.harmonics)
    x = s.x.copy()
    x[7] += 1e-9
    frf.step_response(s.t, x, s.u, s.f_hz)
    frf.step_response(s.t, s.x.astype(np.float32), s.u, s.f_hz)
    frf.step_response(s.t, s.x, s.u, s.f_hz * 1.001)
    frf.step_response(s.t, s.x, s.u, s.f_hz, n_harmonics=2)
    frf.step_response(s.t, s.x, s.u, s.f_hz, fit_frequency=False)
    assert len(fitted) == 6
    frf.step_cache_clear()
    frf.step_response(s.t, s.x, s.u, s.f_hz)
    assert len(fitted) == 7
