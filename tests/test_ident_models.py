"""Models (paper Eq. 8-11): physics against the direct solution of Eq. 3 and the bilinear maps."""

import numpy as np
import pytest
from scipy.signal import bilinear, freqz

from station.ident.models import CoupledModel, DigitalTF, SdofModel, h1_to_continuous, h2_to_continuous

ME, ML = 0.12, 26.167
TH5 = np.array([2e-3, 2.91e7, 17136.0, 4e8, 3000.0])


def direct_eq3(theta: np.ndarray, f: np.ndarray) -> np.ndarray:
    """U/a from Eq. 3a-3b with the base motion prescribed, solved as a 2x2 complex system."""
    S, kf, bf, kc, bc = theta
    out = []
    for fi in f:
        s = 2j * np.pi * fi
        Kf, Kc = kf + s * bf, kc + s * bc
        xb = 1.0 / s**2  # unit base acceleration
        # unknowns x_l, x_e (gravity dropped: linear, static offset only)
        A = np.array([[ML * s**2 + Kc, -Kc], [-Kc, ME * s**2 + Kc + Kf]])
        rhs = np.array([0.0, Kf * xb])
        _, xe = np.linalg.solve(A, rhs)
        out.append(S * kf * (xe - xb))
    return np.array(out)


def test_coupled_model_equals_direct_solution_of_eq3() -> None:
    f = np.linspace(1, 2000, 50)
    got = CoupledModel(ME, ML).response(TH5, f)
    np.testing.assert_allclose(got, direct_eq3(TH5, f), rtol=1e-9)


def test_sdof_is_stiff_limit_and_static_gain_is_minus_S_M() -> None:
    f = np.array([1e-3, 4.0, 100.0])
    stiff = TH5.copy()
    stiff[3], stiff[4] = 1e16, 0.0
    np.testing.assert_allclose(CoupledModel(ME, ML).response(stiff, f),
                               SdofModel(ME, ML).response(TH5[:3], f), rtol=1e-6)
    assert SdofModel(ME, ML).response(TH5[:3], np.array([0.0]))[0] == pytest.approx(-2e-3 * (ME + ML))


def test_sdof_jacobian_matches_finite_differences() -> None:
    from station.ident.models import numeric_jacobian
    m, f = SdofModel(ME, ML), np.array([4.0, 50.0, 150.0])
    np.testing.assert_allclose(m.jacobian(TH5[:3], f), numeric_jacobian(m.response, TH5[:3], f), rtol=1e-6)


@pytest.mark.parametrize("model,theta", [(SdofModel(ME, ML), TH5[:3]), (CoupledModel(ME, ML), TH5)])
def test_paper_coefficients_are_the_bilinear_transform(model, theta) -> None:
    T = 1e-3
    tf = model.to_digital(theta, T)
    num, den = model.polynomials(theta)
    bz, az = bilinear(num, den, fs=1 / T)
    np.testing.assert_allclose(tf.b / tf.a[0], bz, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(tf.a / tf.a[0], az, rtol=1e-9, atol=1e-12)
    # and the digital response approaches the continuous one well below Nyquist
    _, h = freqz(tf.b, tf.a, worN=np.array([4.0]), fs=1 / T)
    assert abs(h[0] / model.response(theta, np.array([4.0]))[0] - 1) < 1e-4


@pytest.mark.parametrize("model,theta", [(SdofModel(ME, ML), TH5[:3]), (CoupledModel(ME, ML), TH5)])
def test_digital_to_physical_round_trip_any_scale(model, theta) -> None:
    T = 2e-3
    tf = model.to_digital(theta, T)
    for scale in (1.0, -2.0, 0.37):
        back = model.from_digital(DigitalTF(tf.b * scale, tf.a * scale, T))
        np.testing.assert_allclose(back, theta, rtol=1e-7)


def test_inverse_maps_recover_continuous_coefficients() -> None:
    m = CoupledModel(ME, ML)
    tf = m.to_digital(TH5, 1e-3)
    d1, d2, d3, d4, n1, n2, rho = h1_to_continuous(tf.b, tf.a, 1e-3)
    np.testing.assert_allclose([d1, d2, d3, d4, n1, n2], m.coefficients(TH5), rtol=1e-7)
    assert rho == pytest.approx(-TH5[0] * TH5[1], rel=1e-9)
    s = SdofModel(ME, ML)
    tf2 = s.to_digital(TH5[:3], 1e-3)
    d1p, d2p, _ = h2_to_continuous(tf2.b, tf2.a, 1e-3)
    assert (d1p, d2p) == pytest.approx((TH5[2] / s.M, TH5[1] / s.M), rel=1e-9)
