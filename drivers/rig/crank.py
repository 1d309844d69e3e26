"""Crank kinematics: frame displacement as a periodic function of the crank angle, and its time
derivatives for a crank whose frequency ramps linearly within a block.

x_b(phi) = Re sum_n c_n exp(i n phi).  The ideal sine mechanism (paper Eq. 1) has c_1 = -i r only;
a slider-crank with a finite rod adds even harmonics (``CrankHarmonics``).
With phi' = W (rad/s) and phi'' = alpha (rad/s^2, constant within a block):
    a    = x''(phi) W^2 + x'(phi) alpha                       (paper Eq. 2 when alpha = 0)
    jerk = x'''(phi) W^3 + 3 x''(phi) W alpha
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.rig.params import CrankHarmonics

_TOL = 1e-12  # harmonics below this fraction of the fundamental are dropped


def displacement_coefficients(radius_m: float, harmonics: CrankHarmonics | None) -> np.ndarray:
    """Complex Fourier coefficients c_1..c_N (m) of x_b(phi), DC removed. Shape (N,)."""
    if harmonics is None:
        return np.array([-1j * radius_m])
    L = harmonics.rod_length_m
    if radius_m >= L:
        raise ValueError(f"rod_length_m must exceed the crank radius {radius_m} m, got {L} m")
    n = 512
    phi = 2 * np.pi * np.arange(n) / n
    rc2 = (radius_m * np.cos(phi)) ** 2
    # sqrt(L^2 - r^2 cos^2) - L written without cancellation
    x = radius_m * np.sin(phi) - rc2 / (L + np.sqrt(L**2 - rc2))
    spec = np.fft.fft(x) / n
    c = 2.0 * spec[1 : n // 2]
    keep = np.nonzero(np.abs(c) > _TOL * radius_m)[0]
    return c[: keep[-1] + 1] if keep.size else c[:1]


@dataclass(frozen=True)
class Kinematics:
    """Displacement (m), acceleration (m/s^2) and jerk (m/s^3) at the sample instants, shape (n,)."""

    displacement: np.ndarray
    acceleration: np.ndarray
    jerk: np.ndarray


ROTATION_ROW = 256  # samples per row of ``rotations`` (kernels.SYNTH_TILE: the compiled synthesis's tile)


def rotations(phi0: float, dphi: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """exp(i phi_k), phi_k = phi0 + dphi*k, k = 0..n-1, as base[k // ROTATION_ROW] * table[k % ROTATION_ROW]:
    (base, table) as real and imaginary parts, shapes (2, ceil(n / ROTATION_ROW)) and (2, ROTATION_ROW)."""
    return rotation_base(phi0, dphi, n), rotation_table(dphi)


def rotation_table(dphi: float) -> np.ndarray:
    """The table of ``rotations``: exp(i dphi k), k < ROTATION_ROW, real and imaginary parts (2, ROTATION_ROW)."""
    table = np.exp(1j * dphi * np.arange(ROTATION_ROW))
    return np.stack([table.real, table.imag])


def rotation_base(phi0: float, dphi: float, n: int) -> np.ndarray:
    """The base of ``rotations``: exp(i (phi0 + dphi ROTATION_ROW j)), j < ceil(n / ROTATION_ROW), (2, rows)."""
    angle = phi0 + dphi * ROTATION_ROW * np.arange(-(-n // ROTATION_ROW))
    base = np.empty((2, angle.size))
    np.cos(angle, out=base[0])
    np.sin(angle, out=base[1])
    return base


def cos_sin(phi0: float, dphi: float, c: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of phi_k = phi0 + dphi*k + c*k^2, k = 0..n-1.

    For c == 0 (steady crank) the angles are built from a table of rotations by dphi (``rotations``:
    one complex product per sample instead of two transcendental calls), the product written out in
    real arithmetic (numpy's complex product fuses a multiply-add on some CPUs: this gives the same
    bits on every machine, and the same as the compiled synthesis); otherwise np.cos/np.sin are used.
    """
    if c != 0.0:
        k = np.arange(n, dtype=float)
        phi = phi0 + k * (dphi + c * k)
        return np.cos(phi), np.sin(phi)
    (br, bi), (tr, ti) = rotations(phi0, dphi, n)
    br, bi = br[:, None], bi[:, None]
    return (br * tr - bi * ti).ravel()[:n], (br * ti + bi * tr).ravel()[:n]


def harmonic_stack(cs: tuple[np.ndarray, np.ndarray], count: int) -> np.ndarray:
    """Rows cos(k phi) for k = 1..count, then sin(k phi) for k = 1..count; shape (2*count, n).

    Chebyshev recurrence: cos((k+1)p) = 2 cos(p) cos(kp) - cos((k-1)p), likewise for sin."""
    c1, s1 = cs
    out = np.empty((2 * count, c1.size))
    out[0], out[count] = c1, s1
    if count > 1:
        two_c1 = 2.0 * c1
        np.multiply(two_c1, c1, out=out[1])
        out[1] -= 1.0
        np.multiply(two_c1, s1, out=out[count + 1])
        for k in range(2, count):
            np.multiply(two_c1, out[k - 1], out=out[k])
            out[k] -= out[k - 2]
            np.multiply(two_c1, out[count + k - 1], out=out[count + k])
            out[count + k] -= out[count + k - 2]
    return out


def harmonic_weights(coeffs: np.ndarray) -> np.ndarray:
    """Rows that give x, dx/dphi, d2x/dphi2, d3x/dphi3 from ``harmonic_stack``; shape (4, 2K).

    With c_k = a_k - i b_k: x = sum a_k cos + b_k sin, x' = sum k (b_k cos - a_k sin),
    x'' = -sum k^2 (a_k cos + b_k sin), x''' = -sum k^3 (b_k cos - a_k sin)."""
    k = np.arange(1, coeffs.size + 1, dtype=float)
    a, b = coeffs.real, -coeffs.imag
    return np.array([np.concatenate([a, b]), np.concatenate([k * b, -k * a]),
                     np.concatenate([-(k**2) * a, -(k**2) * b]), np.concatenate([-(k**3) * b, k**3 * a])])


def harmonic_sum(cs: tuple[np.ndarray, np.ndarray], W: np.ndarray) -> np.ndarray:
    """W @ harmonic_stack(cs, K) without the stack: sum_h W[i, h-1] cos(h phi) + W[i, K+h-1] sin(h phi);
    W: (m, 2K), cs: (cos phi, sin phi), each (n,); returns (m, n).  Compiled (``kernels``)."""
    from drivers.rig import kernels  # numba: imported (and compiled or read from its cache) on first use

    c1, s1 = (np.ascontiguousarray(v, dtype=float) for v in cs)
    out = np.empty((W.shape[0], c1.size))
    kernels.harmonic_series(c1, s1, np.ascontiguousarray(W, dtype=float), out)
    return out


def _series(coeffs: np.ndarray, cs: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """x(phi) and dx/dphi for x = sum_k a_k cos(k phi) + b_k sin(k phi), c_k = a_k - i b_k."""
    xd = harmonic_sum(cs, harmonic_weights(coeffs)[:2])
    return xd[0], xd[1]


def evaluate(coeffs: np.ndarray, cs: tuple[np.ndarray, np.ndarray], omega: np.ndarray | float,
             alpha: float) -> Kinematics:
    """Kinematics of x_b(phi(t)); cs = (cos phi, sin phi), each (n,); omega: crank rate in rad/s,
    (n,) or a scalar for a steady block; alpha: angular acceleration in rad/s^2."""
    w2 = omega * omega
    if coeffs.size == 1:
        a, b = coeffs.real[0], -coeffs.imag[0]
        c1, s1 = cs
        x = b * s1 if a == 0.0 else a * c1 + b * s1
        d1 = b * c1 if a == 0.0 else b * c1 - a * s1
        if alpha == 0.0:
            return Kinematics(displacement=x, acceleration=-w2 * x, jerk=-(w2 * omega) * d1)
        return Kinematics(displacement=x, acceleration=alpha * d1 - w2 * x,
                          jerk=-(w2 * omega) * d1 - 3.0 * alpha * omega * x)
    x, d1, d2, d3 = harmonic_sum(cs, harmonic_weights(coeffs))
    if alpha == 0.0:
        return Kinematics(displacement=x, acceleration=d2 * w2, jerk=d3 * (w2 * omega))
    return Kinematics(displacement=x, acceleration=d2 * w2 + d1 * alpha,
                      jerk=d3 * (w2 * omega) + 3.0 * alpha * d2 * omega)


def displacement_at(coeffs: np.ndarray, cs: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """x_b(phi) in m for cs = (cos phi, sin phi), each (n,)."""
    return _series(coeffs, cs)[0]


def displacement_at_angle(coeffs: np.ndarray, phi: float) -> float:
    """x_b(phi) in m at one crank angle phi (rad): ``displacement_at`` in plain numpy (nothing compiled)."""
    K = coeffs.size
    h = np.arange(1, K + 1) * phi
    w = harmonic_weights(coeffs)[0]
    return float(w[:K] @ np.cos(h) + w[K:] @ np.sin(h))


def displacement_and_slope(coeffs: np.ndarray, cs: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """x_b(phi) in m and dx_b/dphi in m/rad (times the crank rate: the velocity)."""
    return _series(coeffs, cs)


def shift_angle(cs: tuple[np.ndarray, np.ndarray], delta: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of (phi - delta) from cs = (cos phi, sin phi); delta in rad, scalar or (n,)."""
    cd, sd = shift_cos_sin(delta)
    c, s = cs
    return c * cd + s * sd, s * cd - c * sd


def shift_cos_sin(delta: np.ndarray | float) -> tuple[np.ndarray | float, np.ndarray | float]:
    """cos and sin of the lag delta (rad, scalar or (n,)) as ``shift_angle`` uses them: a Taylor
    series when every |delta| < 0.1 (the compiled synthesis computes the same per sample)."""
    if np.ndim(delta) == 0:
        return np.cos(delta), np.sin(delta)
    if np.max(np.abs(delta)) < 0.1:  # Taylor to delta^6: error < 2e-12
        d2 = delta * delta
        return (1.0 - d2 * (0.5 - d2 * (1.0 / 24.0 - d2 / 720.0)),
                delta * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0 - d2 / 5040.0))))
    return np.cos(delta), np.sin(delta)
