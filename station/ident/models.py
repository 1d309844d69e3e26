"""Transducer models of the paper: continuous Eq. 8/9, digital Eq. 10/11, and the maps both ways.

Conventions (SI): input = frame acceleration a (m/s^2), output = force signal U (V) with
``U = S * k_f * Z2`` (Z2 = x_e - x_b, S = total sensitivity in V/N).  Hence, with M = m_e + m_l,

* stiff coupling (Eq. 9):   H(s) = -S k_f / (s^2 + d1' s + d2'),  d1' = b_f/M, d2' = k_f/M,
  i.e. H(s) = -S M k_f / (M s^2 + b_f s + k_f); static limit H(0) = -S M.
* coupled (Eq. 8):          H(s) = -S k_f (s^2 + n1 s + n2) / (s^4 + d1 s^3 + d2 s^2 + d3 s + d4)
  with the paper's d_i, n_i; static limit also -S M.

The paper's gain rho (Eq. 10/11, "-rho Z2/(s^2 X_b)") is therefore ``rho = -S k_f`` (V/m).
The bilinear transform s = (2/T)(1 - z^-1)/(1 + z^-1) gives the paper's coefficient formulas;
they are implemented literally (Eq. 10, Eq. 11) and inverted up to the common scale that a
transfer function's coefficients never fix.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]

# Eq. 10 written as a = MAT_A @ [d4 T^4, d3 T^3, d2 T^2, d1 T, 1]
_MAT_A = np.array([[1, 2, 4, 8, 16], [4, 4, 0, -16, -64], [6, 0, -8, 0, 96],
                   [4, -4, 0, 16, -64], [1, -2, 4, -8, 16]], dtype=float)
# Eq. 10 numerator: b = MAT_B @ [n2 rho T^4, n1 rho T^3, rho T^2]
_MAT_B = np.array([[1, 2, 4], [4, 4, 0], [6, 0, -8], [4, -4, 0], [1, -2, 4]], dtype=float)


@dataclass(frozen=True)
class DigitalTF:
    """Digital transfer function B(z^-1)/A(z^-1): b, a coefficient arrays (ascending powers of z^-1),
    sample period T in s.  Input m/s^2, output V."""

    b: FloatArray
    a: FloatArray
    T: float


@dataclass(frozen=True)
class SdofModel:
    """Eq. 9 (stiff coupling).  Parameters theta = (S [V/N], k_f [N/m], b_f [N s/m]).

    m_e: end mass in kg, m_l: load mass (top mass + adaption) in kg; both known.
    """

    m_e: float
    m_l: float
    key: str = "sdof"
    names: tuple[str, ...] = ("S", "k_f", "b_f")
    units: tuple[str, ...] = ("V/N", "N/m", "N*s/m")

    @property
    def M(self) -> float:
        return self.m_e + self.m_l

    def polynomials(self, theta: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Continuous H(s) = num(s)/den(s), descending powers (scipy convention)."""
        S, k, b = np.asarray(theta, dtype=float)
        return np.array([-S * k]), np.array([1.0, b / self.M, k / self.M])

    def response(self, theta: ArrayLike, f_hz: ArrayLike) -> ComplexArray:
        """H(j 2 pi f) in V/(m/s^2), shape of f_hz.  Eq. 9 times -S k_f."""
        S, k, b = np.asarray(theta, dtype=float)
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        H: ComplexArray = -S * self.M * k / (self.M * s**2 + b * s + k)
        return H

    def jacobian(self, theta: ArrayLike, f_hz: ArrayLike) -> ComplexArray:
        """dH/dtheta, shape (n_f, 3), analytic."""
        S, k, b = np.asarray(theta, dtype=float)
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        D = self.M * s**2 + b * s + k
        H = -S * self.M * k / D
        return np.column_stack([H / S, H * (1.0 / k - 1.0 / D), -H * s / D])

    def to_digital(self, theta: ArrayLike, T: float) -> DigitalTF:
        """Eq. 11 with d1' = b_f/M, d2' = k_f/M, rho = -S k_f."""
        S, k, b = np.asarray(theta, dtype=float)
        return h2_coefficients(b / self.M, k / self.M, -S * k, T)

    def from_digital(self, tf: DigitalTF) -> FloatArray:
        """Inverse of Eq. 11 with the known masses: theta = (S, k_f, b_f)."""
        d1, d2, rho = h2_to_continuous(tf.b, tf.a, tf.T)
        k = d2 * self.M
        return np.array([-rho / k, k, d1 * self.M])


@dataclass(frozen=True)
class CoupledModel:
    """Eq. 8 (finite coupling k_c, b_c).  theta = (S, k_f, b_f, k_c, b_c); masses known (kg)."""

    m_e: float
    m_l: float
    key: str = "coupled"
    names: tuple[str, ...] = ("S", "k_f", "b_f", "k_c", "b_c")
    units: tuple[str, ...] = ("V/N", "N/m", "N*s/m", "N/m", "N*s/m")

    @property
    def M(self) -> float:
        return self.m_e + self.m_l

    def coefficients(self, theta: ArrayLike) -> tuple[float, float, float, float, float, float]:
        """The paper's (d1, d2, d3, d4, n1, n2) of Eq. 8 (units s^-1 ... s^-4)."""
        _, kf, bf, kc, bc = np.asarray(theta, dtype=float)
        me, ml = self.m_e, self.m_l
        u1 = ml * me / (ml + me)
        d1 = bc / u1 + bf / me
        d2 = kc / u1 + kf / me + bf * bc / (me * ml)
        d3 = (kf * bc + kc * bf) / (me * ml)
        d4 = kf * kc / (me * ml)
        return d1, d2, d3, d4, bc / u1, kc / u1

    def polynomials(self, theta: ArrayLike) -> tuple[FloatArray, FloatArray]:
        S, kf = float(np.asarray(theta)[0]), float(np.asarray(theta)[1])
        d1, d2, d3, d4, n1, n2 = self.coefficients(theta)
        return -S * kf * np.array([1.0, n1, n2]), np.array([1.0, d1, d2, d3, d4])

    def response(self, theta: ArrayLike, f_hz: ArrayLike) -> ComplexArray:
        """H(j 2 pi f) in V/(m/s^2): Eq. 8 times -S k_f."""
        num, den = self.polynomials(theta)
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        return np.polyval(num, s) / np.polyval(den, s)

    def jacobian(self, theta: ArrayLike, f_hz: ArrayLike) -> ComplexArray:
        """dH/dtheta, shape (n_f, 5), analytic: H = -S k_f N/D with N = s^2 + n1 s + n2 and
        D = s^4 + d1 s^3 + d2 s^2 + d3 s + d4 (``coefficients``), so for p in (k_f, b_f, k_c, b_c)
        dH/dp = -S (dk_f/dp N/D + k_f (dN/dp D - N dD/dp)/D^2), the coefficients' derivatives below."""
        S, kf, bf, kc, bc = np.asarray(theta, dtype=float)
        d1, d2, d3, d4, n1, n2 = self.coefficients(theta)
        me, ml = self.m_e, self.m_l
        iu, mm = (ml + me) / (ml * me), 1.0 / (me * ml)  # 1/u1, 1/(m_e m_l)
        s = 2j * np.pi * np.asarray(f_hz, dtype=float)
        s2 = s * s
        N = s2 + n1 * s + n2
        D = s2 * s2 + d1 * s2 * s + d2 * s2 + d3 * s + d4
        ND = N / D
        # (dd1, dd2, dd3, dd4, dn1, dn2) per parameter k_f, b_f, k_c, b_c
        dc = ((0.0, 1.0 / me, bc * mm, kc * mm, 0.0, 0.0),
              (1.0 / me, bc * mm, kc * mm, 0.0, 0.0, 0.0),
              (0.0, iu, bf * mm, kf * mm, 0.0, iu),
              (iu, bf * mm, kf * mm, 0.0, iu, 0.0))
        cols = [-kf * ND]
        for i, (e1, e2, e3, e4, m1, m2) in enumerate(dc):
            dN = m1 * s + m2
            dD = e1 * s2 * s + e2 * s2 + e3 * s + e4
            cols.append(-S * ((1.0 if i == 0 else 0.0) * ND + kf * (dN - ND * dD) / D))
        return np.column_stack(cols)

    def to_digital(self, theta: ArrayLike, T: float) -> DigitalTF:
        S, kf = float(np.asarray(theta)[0]), float(np.asarray(theta)[1])
        d1, d2, d3, d4, n1, n2 = self.coefficients(theta)
        return h1_coefficients(d1, d2, d3, d4, n1, n2, -S * kf, T)

    def from_digital(self, tf: DigitalTF) -> FloatArray:
        """Inverse of Eq. 10 with known masses: k_c = n2 u1, b_c = n1 u1, k_f = d4 m_e m_l / k_c,
        b_f = (d1 - n1) m_e, S = -rho/k_f (d2, d3 are redundant and not used)."""
        d1, _d2, _d3, d4, n1, n2, rho = h1_to_continuous(tf.b, tf.a, tf.T)
        me, ml = self.m_e, self.m_l
        u1 = ml * me / (ml + me)
        kc, bc = n2 * u1, n1 * u1
        kf = d4 * me * ml / kc
        return np.array([-rho / kf, kf, (d1 - n1) * me, kc, bc])


Model = SdofModel | CoupledModel


def make_model(key: str, m_e: float, m_l: float) -> Model:
    """'sdof'/'h2' -> SdofModel, 'coupled'/'h1' -> CoupledModel."""
    if key in ("sdof", "h2"):
        return SdofModel(m_e, m_l)
    if key in ("coupled", "h1"):
        return CoupledModel(m_e, m_l)
    raise ValueError(f"unknown model {key!r}")


def numeric_jacobian(fun: Callable[[FloatArray, ArrayLike], ComplexArray], theta: ArrayLike, f_hz: ArrayLike,
                     rel_step: float = 1e-6, typical: ArrayLike | None = None) -> ComplexArray:
    """Central-difference Jacobian of a complex model fun(theta, f) -> (n_f,), shape (n_f, n_theta);
    step rel_step * max(|theta_i|, typical_i)."""
    th = np.asarray(theta, dtype=float)
    typ = np.zeros(th.size) if typical is None else np.asarray(typical, dtype=float)
    cols = []
    for i in range(th.size):
        h = rel_step * max(abs(th[i]), typ[i], 1e-300)
        tp, tm = th.copy(), th.copy()
        tp[i] += h
        tm[i] -= h
        cols.append((fun(tp, f_hz) - fun(tm, f_hz)) / (2 * h))
    return np.column_stack(cols)


def h2_coefficients(d1: float, d2: float, rho: float, T: float) -> DigitalTF:
    """Eq. 11: a0' = d2 T^2 + 2 d1 T + 4, a1' = 2 d2 T^2 - 8, a2' = d2 T^2 - 2 d1 T + 4,
    b1' = 2 rho T^2, b0' = b2' = b1'/2 (bilinear transform of rho/(s^2 + d1 s + d2))."""
    a = np.array([d2 * T**2 + 2 * d1 * T + 4, 2 * d2 * T**2 - 8, d2 * T**2 - 2 * d1 * T + 4])
    b1 = 2 * rho * T**2
    return DigitalTF(np.array([b1 / 2, b1, b1 / 2]), a, T)


def h2_to_continuous(b: ArrayLike, a: ArrayLike, T: float) -> tuple[float, float, float]:
    """Inverse of Eq. 11 up to the common scale c = (a0 - a1 + a2)/16: returns (d1', d2', rho).

    d2' = (a0 + a1 + a2)/(4 c T^2), d1' = (a0 - a2)/(4 c T), rho = (b0 + b1 + b2)/(4 c T^2)
    (the numerator sum uses all three b so that a PSO particle that breaks b0 = b2 = b1/2 still maps).
    """
    a0, a1, a2 = np.asarray(a, dtype=float)
    c = (a0 - a1 + a2) / 16.0
    d2 = (a0 + a1 + a2) / (4 * c * T**2)
    d1 = (a0 - a2) / (4 * c * T)
    rho = float(np.sum(b)) / (4 * c * T**2)
    return float(d1), float(d2), float(rho)


def h1_coefficients(d1: float, d2: float, d3: float, d4: float, n1: float, n2: float, rho: float,
                    T: float) -> DigitalTF:
    """Eq. 10 (bilinear transform of rho (s^2 + n1 s + n2)/(s^4 + d1 s^3 + d2 s^2 + d3 s + d4))."""
    a = _MAT_A @ np.array([d4 * T**4, d3 * T**3, d2 * T**2, d1 * T, 1.0])
    b = _MAT_B @ np.array([n2 * rho * T**4, n1 * rho * T**3, rho * T**2])
    return DigitalTF(b, a, T)


def h1_to_continuous(b: ArrayLike, a: ArrayLike, T: float) -> tuple[float, ...]:
    """Inverse of Eq. 10: returns (d1, d2, d3, d4, n1, n2, rho); scale from the '16' column, the
    numerator by least squares on the 5 x 3 system (exact for coefficients of the form Eq. 10)."""
    v = np.linalg.solve(_MAT_A, np.asarray(a, dtype=float))
    c = v[4]
    d4, d3, d2, d1 = v[0] / (c * T**4), v[1] / (c * T**3), v[2] / (c * T**2), v[3] / (c * T)
    w = np.linalg.lstsq(_MAT_B, np.asarray(b, dtype=float) / c, rcond=None)[0]
    rho = w[2] / T**2
    n2, n1 = w[0] / (rho * T**4), w[1] / (rho * T**3)
    return float(d1), float(d2), float(d3), float(d4), float(n1), float(n2), float(rho)
